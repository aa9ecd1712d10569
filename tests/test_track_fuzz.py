"""Property-based fuzzing of the track reader (hypothesis).

Every generated file either loads, with the invariants of SPEC §1, or raises TrackError whose
message names the file and, for a row-level fault planted at a known place, the line and column
of that fault. Nothing else may escape. The number of cases tried per property is printed at
the end of the module (``pytest -s``) and must reach a floor.
"""
from __future__ import annotations

import collections
import gzip
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests._corruption import corrupt
from streamcal.inputs import trackio
from streamcal.errors import TrackError
from streamcal.inputs.track import Track
from streamcal.inputs.trackio import NUMBER

FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
NAME = "fuzz_track.csv"
TRIED: collections.Counter = collections.Counter()
MIN_TRIED = 100  # per property; hypothesis stops early only if it runs out of distinct inputs


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz")
    yield path
    print("\ntrack reader fuzz cases tried:", dict(TRIED), "total", sum(TRIED.values()))


# ----------------------------------------------------------------------------- valid tracks

finite = st.floats(allow_nan=False, allow_infinity=False)
pad = st.sampled_from(["", "", "", " ", "\t"])


@st.composite
def valid_tracks(draw):
    """(metadata lines, column names, rows of cell strings, expected values (R,C) NaN=empty)."""
    names = ["t", "mx", "my", "mz"]
    names += draw(st.sampled_from([[], ["ax", "ay", "az"], ["ax", "ay", "az", "gx", "gy", "gz"]]))
    names += draw(st.sampled_from([[], ["temp"], ["temp", "current"]]))
    names = draw(st.permutations(names))
    nrow, ncol = draw(st.integers(1, 15)), len(names)
    times = sorted(draw(st.lists(st.floats(0, 1e6), min_size=nrow, max_size=nrow)))
    cells = np.array(draw(st.lists(finite, min_size=nrow * ncol, max_size=nrow * ncol)))
    values = cells.reshape(nrow, ncol)
    values[:, names.index("t")] = times
    groups = [("mx", "my", "mz"), ("ax", "ay", "az"), ("gx", "gy", "gz"), ("temp",), ("current",)]
    sampled = draw(st.lists(st.integers(0, 31), min_size=nrow, max_size=nrow))
    for r, bits in enumerate(sampled):  # bit k set: group k sampled on row r
        for k, group in enumerate(groups):
            if not bits >> k & 1:
                values[r, [names.index(n) for n in group if n in names]] = np.nan
    left, right = draw(pad), draw(pad)
    rows = [[("" if math.isnan(v) else left + repr(float(v)) + right) for v in row]
            for row in values]
    meta = draw(st.lists(st.sampled_from(["# streamcal-track: 1", "# sensor: mpu9250",
                                          "# mag_unit: counts (0.15 uT/LSB)", "", "# note"]),
                         max_size=4))
    return meta, names, rows, values


def render(meta, names, rows) -> str:
    return "\n".join(meta + [",".join(names)] + [",".join(row) for row in rows]) + "\n"


def first_data_line(meta) -> int:
    return len(meta) + 2


def store(workdir, text_or_bytes, zipped: bool = False):
    data = text_or_bytes.encode("utf-8") if isinstance(text_or_bytes, str) else text_or_bytes
    path = workdir / (NAME + (".gz" if zipped else ""))
    path.write_bytes(gzip.compress(data) if zipped else data)
    return path


def read_expecting_error(path, line, column, **kw) -> TrackError:
    with pytest.raises(TrackError) as err:
        Track.read(path, **kw)
    assert path.name in str(err.value)
    assert (err.value.line, err.value.column) == (line, column), str(err.value)
    return err.value


# ----------------------------------------------------------------------------- properties


@pytest.mark.slow
@FUZZ
@given(track=valid_tracks(), zipped=st.booleans())
def test_valid_files_load_exactly(workdir, track, zipped):
    TRIED["valid"] += 1
    meta, names, rows, values = track
    loaded = Track.read(store(workdir, render(meta, names, rows), zipped))
    assert len(loaded) == len(rows)
    for j, name in enumerate(names):
        np.testing.assert_array_equal(loaded.columns[name], values[:, j])
    assert np.all(np.diff(loaded.t) >= 0) and np.all(np.isfinite(loaded.mag))


def bad_tokens():
    words = st.text(st.characters(blacklist_characters=",\n\r", blacklist_categories=["Cs"]),
                    min_size=1, max_size=12)
    words = words.filter(lambda s: s.strip(" \t") != "" and not NUMBER.fullmatch(s.strip(" \t")))
    specials = st.sampled_from(["nan", "NaN", "inf", "-inf", "Infinity", "1e999", "-1e400",
                                "1.2.3", "1e", "--1", "0x1A", "1_000", "١٢", "1e+", "\x00"])
    return st.one_of(words, specials)


@pytest.mark.slow
@FUZZ
@given(track=valid_tracks(), data=st.data(), zipped=st.booleans())
def test_bad_cell_is_located(workdir, track, data, zipped):
    TRIED["bad_cell"] += 1
    meta, names, rows, _ = track
    r = data.draw(st.integers(0, len(rows) - 1))
    c = data.draw(st.integers(0, len(names) - 1))
    token = data.draw(bad_tokens())
    if c == 0 and token.lstrip(" \t").startswith("#"):
        token = "x" + token  # a data line starting with '#' is a comment, not a bad cell
    rows[r][c] = token
    path = store(workdir, render(meta, names, rows), zipped)
    err = read_expecting_error(path, first_data_line(meta) + r, names[c])
    assert any(word in err.reason for word in ("not a number", "non-finite", "overflows"))
    if len(rows) > 1:
        kept = Track.read(path, skip_bad_rows=True)
        assert kept.skipped_rows == 1 and len(kept) == len(rows) - 1


@pytest.mark.slow
@FUZZ
@given(track=valid_tracks(), data=st.data())
def test_wrong_cell_count_is_located(workdir, track, data):
    TRIED["cell_count"] += 1
    meta, names, rows, _ = track
    r = data.draw(st.integers(0, len(rows) - 1))
    extra = data.draw(st.booleans())
    if extra:
        rows[r].insert(data.draw(st.integers(0, len(rows[r]))), data.draw(st.sampled_from(
            ["", "1", "2.5"])))
    else:
        del rows[r][data.draw(st.integers(1, len(rows[r]) - 1))]
    column = None if extra else names[-1]
    err = read_expecting_error(store(workdir, render(meta, names, rows)),
                               first_data_line(meta) + r, column)
    assert f"expected {len(names)} cells" in err.reason


@pytest.mark.slow
@FUZZ
@given(track=valid_tracks().filter(lambda tr: len(tr[2]) >= 2), data=st.data())
def test_backwards_time_is_located(workdir, track, data):
    TRIED["backwards"] += 1
    meta, names, rows, values = track
    r = data.draw(st.integers(1, len(rows) - 1))
    tc = names.index("t")
    previous = values[r - 1, tc]
    rows[r][tc] = repr(previous - data.draw(st.floats(1e-3, 1e3)) - abs(previous) * 1e-12)
    read_expecting_error(store(workdir, render(meta, names, rows)), first_data_line(meta) + r,
                         "t")


@pytest.mark.slow
@FUZZ
@given(track=valid_tracks(), data=st.data())
def test_partial_mag_row_is_located(workdir, track, data):
    TRIED["partial_mag"] += 1
    meta, names, rows, values = track
    r = data.draw(st.integers(0, len(rows) - 1))
    mag_cols = [names.index(n) for n in ("mx", "my", "mz")]
    for j in mag_cols:
        if rows[r][j] == "":
            rows[r][j] = "1.5"
    blank = data.draw(st.lists(st.sampled_from(["mx", "my", "mz"]), min_size=1, max_size=2,
                               unique=True))
    for name in blank:
        rows[r][names.index(name)] = data.draw(pad)
    first = min(blank, key=["mx", "my", "mz"].index)
    err = read_expecting_error(store(workdir, render(meta, names, rows)),
                               first_data_line(meta) + r, first)
    assert "partial mag" in err.reason


@FUZZ
@given(tokens=st.lists(st.text(alphabet="0123456789eE.+- \t", max_size=9), min_size=1,
                       max_size=6))
def test_fast_and_slow_parsers_agree_on_plain_characters(tokens):
    """The fast path (loadtxt) must accept exactly what NUMBER accepts, with the same values."""
    TRIED["fast_vs_slow"] += 1
    lines = [f"{i},{tok},1,1" for i, tok in enumerate(tokens)]
    fast = trackio._parse_fast("\n".join(lines), len(lines), 4)
    slow, problems = trackio._parse_slow(lines, ["t", "mx", "my", "mz"])
    if fast is None:  # the fast path may only decline bad cells or blank-but-not-empty ones
        assert problems or any(tok and not tok.strip(" \t") for tok in tokens), tokens
    else:
        assert not problems
        np.testing.assert_array_equal(fast, slow)


chaos_ops = st.sampled_from(["truncate", "insert_bytes", "flip", "utf16", "latin1", "gzip_cut",
                             "gzip_garbage", "empty", "only_meta", "nul", "huge", "swap_lines",
                             "crlf", "blank_lines", "gzip"])


@FUZZ
@given(track=valid_tracks(), ops=st.lists(chaos_ops, min_size=1, max_size=3), data=st.data(),
       skip=st.booleans())
@pytest.mark.slow
def test_chaos_loads_or_raises_track_error(workdir, track, ops, data, skip):
    TRIED["chaos"] += 1
    meta, names, rows, _ = track
    if "huge" in ops:
        r = data.draw(st.integers(0, len(rows) - 1))
        c = data.draw(st.integers(0, len(names) - 1))
        rows[r][c] = data.draw(st.sampled_from(["1e308", "-1.7976931348623157e308", "1e309",
                                                "4.9e-324", "-0.0"]))
    text = render(meta, names, rows)
    if "swap_lines" in ops and len(rows) > 1:
        lines = text.split("\n")
        i, j = sorted(data.draw(st.lists(st.integers(0, len(lines) - 1), min_size=2,
                                         max_size=2, unique=True)))
        lines[i], lines[j] = lines[j], lines[i]
        text = "\n".join(lines)
    blob = corrupt(text, ops, data)
    path = store(workdir, blob)
    try:
        track_ = Track.read(path, skip_bad_rows=skip)
    except TrackError as err:
        assert NAME in str(err)
        if err.line is not None:
            assert err.line >= 1
        return
    TRIED["chaos_loaded"] += 1
    assert len(track_) > 0
    assert np.all(np.diff(track_.t) >= 0) and np.all(np.isfinite(track_.t))
    assert np.all(np.isfinite(track_.mag))
    assert not any(np.isinf(col).any() for col in track_.columns.values())


def test_enough_cases_were_tried():
    properties = ["valid", "bad_cell", "cell_count", "backwards", "partial_mag", "chaos",
                  "fast_vs_slow"]
    if not all(TRIED[p] for p in properties):
        pytest.skip("run the whole module to count the cases")
    assert all(TRIED[p] >= MIN_TRIED for p in properties), dict(TRIED)
