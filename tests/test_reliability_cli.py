"""Malformed track files through the command line, in process: exit codes and messages.

Every generated file goes through ``streamcal.cli.main(["fit", path])`` with stdout/stderr
captured. The contract (SPEC §1, §4): exit 2 with a message naming the file — and, for a
row-level fault planted at a known place, its line and column — or 0/1 when the file happens to be
valid; never a traceback, never an exception escaping ``main``. The number of cases tried is
printed at the end of the module (``pytest -s``) and must reach a floor.
"""
from __future__ import annotations

import collections
import contextlib
import gzip
import io
import traceback

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests._corruption import corrupt
from streamcal.cli import main
from streamcal.errors import TrackError
from streamcal.inputs.track import Track
from streamcal.inputs.trackio import NUMBER

FUZZ = settings(max_examples=120, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
TRIED: collections.Counter = collections.Counter()
OUTCOMES: collections.Counter = collections.Counter()
MIN_TRIED = 100


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli_fuzz")
    yield path
    print("\nCLI malformed-track cases tried:", dict(TRIED), "total", sum(TRIED.values()),
          "outcomes", dict(OUTCOMES))


def run_cli(argv) -> tuple[int, str, str]:
    """``main(argv)`` in process; returns (exit code, stdout, stderr). Any exception escaping
    ``main`` (other than SystemExit from argparse) fails the test with the traceback."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse usage errors
            code = exc.code
        except Exception:
            raise AssertionError("exception escaped streamcal.cli.main:\n"
                                 + traceback.format_exc()) from None
    return code, out.getvalue(), err.getvalue()


def check_outcome(path, argv_tail=()) -> tuple[int, str]:
    code, out, err = run_cli(["fit", str(path), *argv_tail])
    OUTCOMES[code] += 1
    assert code in (0, 1, 2), (code, err)
    assert "Traceback" not in err and "Traceback" not in out
    if code == 2:
        assert str(path) in err, err
        assert "error:" in err
    return code, err


# ----------------------------------------------------------------------------- generators

finite = st.floats(allow_nan=False, allow_infinity=False)
HEADER = ["t", "ax", "ay", "az", "mx", "my", "mz", "temp"]


@st.composite
def small_tracks(draw):
    """(metadata lines, names, rows of cell strings); times non-decreasing, cells finite."""
    names = draw(st.permutations(HEADER))
    nrow = draw(st.integers(1, 12))
    times = sorted(draw(st.lists(st.floats(0, 1e5), min_size=nrow, max_size=nrow)))
    rows = []
    for r in range(nrow):
        mag = draw(st.booleans())
        row = []
        for name in names:
            if name == "t":
                row.append(repr(times[r]))
            elif name in ("mx", "my", "mz") and not mag:
                row.append("")
            else:
                row.append(repr(draw(finite)))
        rows.append(row)
    meta = draw(st.lists(st.sampled_from(["# streamcal-track: 1", "# sensor: mpu9250", "",
                                          "# note"]), max_size=3))
    return meta, list(names), rows


def render(meta, names, rows) -> str:
    return "\n".join(meta + [",".join(names)] + [",".join(row) for row in rows]) + "\n"


def bad_tokens():
    words = st.text(st.characters(blacklist_characters=",\n\r#", blacklist_categories=["Cs"]),
                    min_size=1, max_size=10)
    words = words.filter(lambda s: s.strip(" \t\r") != "" and not NUMBER.fullmatch(s.strip()))
    return st.one_of(words, st.sampled_from(["nan", "NaN", "inf", "-Infinity", "1e999", "-1e400",
                                             "1.2.3", "0x10", "1_0", "١", "\x00", "\xff"]))


# ----------------------------------------------------------------------------- row-level faults


@pytest.mark.slow
@FUZZ
@given(track=small_tracks(), data=st.data(), zipped=st.booleans())
def test_bad_cell_exits_2_naming_file_line_column(workdir, track, data, zipped):
    TRIED["bad_cell"] += 1
    meta, names, rows = track
    r = data.draw(st.integers(0, len(rows) - 1))
    c = data.draw(st.integers(0, len(names) - 1))
    rows[r][c] = data.draw(bad_tokens())
    if names[c] in ("mx", "my", "mz"):       # a bad cell in an otherwise empty triple
        for name in ("mx", "my", "mz"):
            j = names.index(name)
            rows[r][j] = rows[r][j] or "1.0"
    blob = render(meta, names, rows).encode("utf-8", errors="surrogateescape")
    path = workdir / ("bad_cell.csv" + (".gz" if zipped else ""))
    path.write_bytes(gzip.compress(blob) if zipped else blob)
    code, err = check_outcome(path)
    assert code == 2
    line = len(meta) + 2 + r
    assert f"{path}:{line} column '{names[c]}'" in err, err


@FUZZ
@given(track=small_tracks(), data=st.data())
def test_wrong_cell_count_exits_2_naming_line(workdir, track, data):
    TRIED["cell_count"] += 1
    meta, names, rows = track
    r = data.draw(st.integers(0, len(rows) - 1))
    if data.draw(st.booleans()):
        rows[r].append(data.draw(st.sampled_from(["", "1", "x"])))
    else:
        rows[r] = rows[r][:data.draw(st.integers(2, len(names) - 1))]   # a truncated line
    path = workdir / "cell_count.csv"
    path.write_text(render(meta, names, rows))
    code, err = check_outcome(path)
    assert code == 2
    assert f"{path}:{len(meta) + 2 + r}" in err and f"expected {len(names)} cells" in err, err


@pytest.mark.slow
@FUZZ
@given(track=small_tracks().filter(lambda tr: len(tr[2]) >= 2), data=st.data())
def test_time_going_backwards_exits_2_naming_line(workdir, track, data):
    TRIED["backwards"] += 1
    meta, names, rows = track
    r = data.draw(st.integers(1, len(rows) - 1))
    tc = names.index("t")
    previous = float(rows[r - 1][tc])
    rows[r][tc] = repr(previous - data.draw(st.floats(1e-3, 1e6)) - abs(previous) * 1e-12)
    path = workdir / "backwards.csv"
    path.write_text(render(meta, names, rows))
    code, err = check_outcome(path)
    assert code == 2
    assert f"{path}:{len(meta) + 2 + r} column 't'" in err and "backwards" in err, err


# ----------------------------------------------------------------------------- whole-file chaos

chaos_ops = st.sampled_from(["truncate", "insert_bytes", "flip", "utf16", "latin1", "gzip_cut",
                             "gzip_garbage", "empty", "only_header", "only_meta", "huge",
                             "binary", "drop_header", "long_line", "gzip"])


@pytest.mark.slow
@FUZZ
@given(track=small_tracks(), ops=st.lists(chaos_ops, min_size=1, max_size=3), data=st.data())
def test_chaos_through_fit_never_tracebacks(workdir, track, ops, data):
    TRIED["chaos"] += 1
    meta, names, rows = track
    if "huge" in ops:
        r = data.draw(st.integers(0, len(rows) - 1))
        c = data.draw(st.integers(0, len(names) - 1))
        rows[r][c] = data.draw(st.sampled_from(["1e308", "-1.7976931348623157e308", "1e300",
                                                "4.9e-324", "1e200"]))
    blob = corrupt(render(meta, names, rows), ops, data)
    path = workdir / "chaos.csv"
    path.write_bytes(blob)
    try:
        Track.read(path)
        readable = True
    except TrackError:
        readable = False
    code, _ = check_outcome(path)
    if not readable:
        assert code == 2                # the reader's verdict reaches the user as exit 2
    OUTCOMES["chaos_readable"] += readable


# ----------------------------------------------------------------------------- valid but hostile

def sphere_rows(n, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x * 45.0 + [5.0, -3.0, 2.0] + 0.3 * rng.standard_normal((n, 3))


HOSTILE = {
    # name: (damage applied to 300 samples on a sphere, exit codes allowed)
    "huge_values": (lambda m: np.vstack([np.full((3, 3), 1e300), m[3:]]), (1, 2)),
    "max_float": (lambda m: np.vstack([np.full((1, 3), -1.7976931348623157e308), m[1:]]), (1, 2)),
    "subnormal": (lambda m: m * 1e-310, (1, 2)),
    "constant": (lambda m: np.full_like(m, 12.5), (1, 2)),
    "dead_axis": (lambda m: m * [1.0, 0.0, 1.0], (1, 2)),
    "spikes": (lambda m: m * np.where(np.arange(len(m)) % 3 == 0, 1e6, 1.0)[:, None], (0, 1, 2)),
    "saturated": (lambda m: np.clip(m, -4912.0, 10.0), (0, 1, 2)),
    "few_rows": (lambda m: m[:4], (1, 2)),
    "constant_12_rows": (lambda m: np.full((12, 3), 12.5), (1, 2)),
    "subnormal_62_rows": (lambda m: m[:62] * 1e-310, (1, 2)),
}
#: These cases used to escape as numpy.linalg.LinAlgError (a traceback) until 62caee4.


def _hostile_params():
    for name in HOSTILE:
        for option in ("", "--method=l2_ellipsoid", "--method=sphere_stream", "--kernel=l2"):
            yield pytest.param(name, option, id=f"{name}{option}")


@pytest.mark.parametrize("case,option", list(_hostile_params()))
def test_valid_files_with_hostile_numbers_never_traceback(tmp_path, case, option):
    """Files that parse but carry readings no sensor makes reach the fitter: an exit code of
    the contract and a message, never a traceback."""
    TRIED["hostile_valid"] += 1
    rng = np.random.default_rng(7)
    x = rng.standard_normal((300, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    damage, allowed = HOSTILE[case]
    m = damage(x * 45.0 + [5.0, -3.0, 2.0] + 0.3 * rng.standard_normal((300, 3)))
    t = np.arange(len(m)) * 0.01
    lines = [f"{a!r},{b!r},{c!r},{d!r}" for a, b, c, d in np.column_stack([t, m]).tolist()]
    path = tmp_path / f"{case}.csv"
    path.write_text("t,mx,my,mz\n" + "\n".join(lines) + "\n")
    code, out, err = run_cli(["fit", str(path)] + ([option] if option else []))
    assert "Traceback" not in err + out
    assert code in allowed, (code, err)
    if code:
        assert "error:" in err


# ----------------------------------------------------------------------------- fixed cases

def _write(path, text):
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def malformed(tmp_path_factory):
    d = tmp_path_factory.mktemp("malformed")
    ok_rows = "\n".join(f"{0.01 * i:.2f},{40 + i % 3},{-20 + i % 5},{30 - i % 7}"
                        for i in range(20))
    return {
        "empty": (_write(d / "empty.csv", ""), None, None),
        "header_only": (_write(d / "header_only.csv", "t,mx,my,mz\n"), None, None),
        "missing_column": (_write(d / "missing.csv", "t,mx,my\n0,1,2\n"), 1, "mz"),
        "text_cell": (_write(d / "text.csv", "t,mx,my,mz\n" + ok_rows + "\n0.3,1,abc,2\n"), 22,
                      "my"),
        "nan_cell": (_write(d / "nan.csv", "t,mx,my,mz\n" + ok_rows + "\n0.3,NaN,1,2\n"), 22,
                     "mx"),
        "inf_cell": (_write(d / "inf.csv", "t,mx,my,mz\n" + ok_rows + "\n0.3,1,2,-inf\n"), 22,
                     "mz"),
        "backwards": (_write(d / "back.csv", "t,mx,my,mz\n" + ok_rows + "\n0.05,1,2,3\n"), 22,
                      "t"),
        "gzip_garbage": (d / "garbage.csv.gz", None, None),
    }


@pytest.fixture(scope="module", autouse=True)
def _gzip_garbage(malformed):
    malformed["gzip_garbage"][0].write_bytes(b"\x1f\x8b\x08\x00garbage" * 10)


@pytest.mark.parametrize("command", ["fit", "diagnose", "replay"])
@pytest.mark.parametrize("case", ["empty", "header_only", "missing_column", "text_cell",
                                  "nan_cell", "inf_cell", "backwards", "gzip_garbage"])
def test_fit_diagnose_replay_report_malformed_files(malformed, command, case, tmp_path):
    path, line, column = malformed[case]
    argv = [command, str(path)] + (["--state-dir", str(tmp_path / "st")]
                                   if command == "replay" else [])
    code, out, err = run_cli(argv)
    TRIED[f"fixed_{command}"] += 1
    assert code == 2, (code, out, err)
    assert "Traceback" not in err + out
    assert str(path) in err
    if line is not None:
        assert f"{path}:{line} column '{column}'" in err, err
    if command == "replay":   # nothing written into a state dir for a file that was refused
        assert not (tmp_path / "st" / "calibration.json").exists()


def test_skip_bad_rows_fits_what_is_left(tmp_path):
    """``--skip-bad-rows`` turns a row-level error into a skipped row, not an exit 2."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal((400, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = x * 45.0 + [5.0, -3.0, 2.0] + 0.2 * rng.standard_normal((400, 3))
    lines = [f"{0.01 * i:.2f},{a!r},{b!r},{c!r}" for i, (a, b, c) in enumerate(m.tolist())]
    lines[100] = "1.00,oops,1,2"
    lines[200] = "2.00,1,2"
    path = _write(tmp_path / "skip.csv", "t,mx,my,mz\n" + "\n".join(lines) + "\n")
    code, out, err = run_cli(["fit", str(path), "--json"])
    assert code == 2 and f"{path}:102 column 'mx'" in err
    code, out, err = run_cli(["fit", str(path), "--json", "--skip-bad-rows"])
    assert code == 0, err
    assert "Traceback" not in err
    import json
    assert json.loads(out)["n"] == 398


def test_enough_cases_were_tried():
    properties = ["bad_cell", "cell_count", "backwards", "chaos"]  # hostile_valid: fewer, fits cost
    if not all(TRIED[p] for p in properties):
        pytest.skip("run the whole module to count the cases")
    assert all(TRIED[p] >= MIN_TRIED for p in properties), dict(TRIED)
    print("\nCLI cases:", sum(TRIED.values()), dict(TRIED), "exit codes:", dict(OUTCOMES))


