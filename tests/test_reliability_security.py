"""Security: strict calibration parsing, private state directory, no writes through planted
symlinks, serial commands with out-of-range values refused before anything is sent."""
from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge import frames as fr
from firmware_bridge.serial_link import SerialLink
from tests._ports import NullPort
from streamcal.calibration import MAX_FILE_BYTES, Calibration
from streamcal.errors import CalibrationFileError, InputError, StreamcalError
from streamcal.stream.store import CalibrationStore

REPO = Path(__file__).resolve().parent.parent


def _good() -> dict:
    return Calibration(K=np.diag([50.0, 48.0, 52.0]), b=[1.0, 2.0, 3.0], rms=0.4, n=100).to_dict()


# ------------------------------------------------------------------------ no code from data

def test_no_pickle_eval_or_unsafe_loaders_in_the_code():
    pattern = re.compile(r"\bpickle\b|\beval\(|\bexec\(|yaml\.load\(|allow_pickle\s*=\s*True|"
                         r"\bmarshal\b|\bshelve\b")
    hits = []
    for package in ("streamcal", "firmware_bridge"):
        for path in (REPO / package).rglob("*.py"):
            for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                code = line.split("#", 1)[0]
                if pattern.search(code) and "never pickle" not in line:
                    hits.append(f"{path.relative_to(REPO)}:{no}: {line.strip()}")
    assert not hits, "\n".join(hits)


# ------------------------------------------------------------------------ strict parsing

BAD_VALUES = {
    # key: (bad value, text expected in the message)
    "format": ("streamcal-calibration/2", "format"),
    "sensor": ("gyro", "sensor"),
    "model": (["hard_iron", "__import__('os')"], "model"),
    "K": ([[50, 0], [0, 48]], "K"),
    "b": ([1, 2, 3, 4], "b"),
    "n": (-5, "n"),
    "rms": ("0.4", "rms"),
    "coverage": (1.5, "coverage"),
    "field_uT": (-48.0, "field_uT"),
    "created": (20240101, "created"),
    "effects": ({"temperature_offset": {"T0": 25.0, "c": [1, 2]}}, "effects"),
}


@pytest.mark.parametrize("key", sorted(BAD_VALUES))
def test_wrong_values_are_refused_naming_the_key(key):
    data = _good()
    data[key], word = BAD_VALUES[key]
    with pytest.raises(CalibrationFileError, match=rf"key '{re.escape(word)}"):
        Calibration.from_json(json.dumps(data), source="cal.json")


NON_FINITE = ['"K": [[NaN, 0, 0], [0, 48, 0], [0, 0, 52]]', '"b": [Infinity, 2, 3]',
              '"K": [[1e999, 0, 0], [0, 48, 0], [0, 0, 52]]', '"rms": -Infinity']


@pytest.mark.parametrize("fragment", NON_FINITE)
def test_non_finite_numbers_are_refused(fragment):
    key = fragment.split('"')[1]
    text = json.dumps(_good())
    text = re.sub(rf'"{key}": (\[\[.*?\]\]|\[.*?\]|[^,}}]+)', fragment, text, count=1)
    assert fragment in text
    with pytest.raises(CalibrationFileError) as err:
        Calibration.from_json(text, source="cal.json")
    assert "cal.json" in str(err.value)


@pytest.mark.parametrize("key,value", [
    ("K", [[50, 0, 0], [0, 48, 0], [0, 0, "52"]]),
    ("b", [True, False, 1]),
    ("unit", 123),
    ("method", ["autocal"]),
    ("kernel", {"a": 1}),
    ("K", "[[50,0,0],[0,48,0],[0,0,52]]"),
    ("K", {"0": [50, 0, 0]}),
    ("b", None),
    ("n", True),
    ("n", 2.5),
    ("model", "hard_iron,soft_iron"),
    ("effects", [1, 2]),
])
def test_wrong_types_are_refused_naming_the_key(key, value):
    data = _good()
    data[key] = value
    with pytest.raises(CalibrationFileError, match=rf"key '{key}"):
        Calibration.from_json(json.dumps(data), source="cal.json")


@pytest.mark.parametrize("text", [
    pytest.param("[" * 100_000 + "]" * 100_000, id="deep_list"),
    pytest.param('{"a": ' * 50_000 + "1" + "}" * 50_000, id="deep_object"),
])
def test_huge_nesting_is_a_calibration_file_error(text):
    with pytest.raises(CalibrationFileError):
        Calibration.from_json(text, source="cal.json")


def test_deep_nesting_in_the_state_dir_falls_back_to_history(tmp_path):
    store = CalibrationStore(tmp_path / "state")
    store.save(Calibration(K=np.diag([50.0, 48.0, 52.0]), b=[1, 2, 3], n=7))
    store.current_path.write_text("[" * 2000 + "]" * 2000)
    result = store.load()
    assert result.calibration.n == 7 and result.fell_back
    assert "cal" in result.problems[0]


def test_oversized_files_are_refused_without_reading_them_whole(tmp_path):
    path = tmp_path / "big.json"
    data = _good()
    data["padding"] = "x" * (MAX_FILE_BYTES + 10)
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="too large"):
        Calibration.load(path)
    store = CalibrationStore(tmp_path / "state")
    os.replace(path, store.current_path)
    result = store.load()
    assert result.calibration is None and "too large" in result.problems[0]


def test_binary_and_non_utf8_files_are_refused(tmp_path):
    path = tmp_path / "cal.json"
    path.write_bytes(b"\x80\x81\xfe\xff" + json.dumps(_good()).encode())
    with pytest.raises(CalibrationFileError, match="UTF-8"):
        Calibration.load(path)
    path.write_bytes(b"\x00" * 100)
    with pytest.raises(CalibrationFileError):
        Calibration.load(path)


# ------------------------------------------------------------------------ the state directory

def test_state_dir_private_even_with_a_permissive_umask(tmp_path):
    old = os.umask(0)
    try:
        loose = tmp_path / "loose"
        loose.mkdir(mode=0o777)
        store = CalibrationStore(loose)
        store.save(Calibration(K=np.eye(3) * 50, b=[0, 0, 0], n=1))
        fresh = CalibrationStore(tmp_path / "a" / "b" / "state")
        fresh.save(Calibration(K=np.eye(3) * 50, b=[0, 0, 0], n=1))
    finally:
        os.umask(old)
    for s in (store, fresh):
        assert stat.S_IMODE(os.stat(s.dir).st_mode) == 0o700
        assert stat.S_IMODE(os.stat(s.history_dir).st_mode) == 0o700
        assert stat.S_IMODE(os.stat(s.current_path).st_mode) == 0o600
        assert all(stat.S_IMODE(os.stat(p).st_mode) == 0o600 for p in s.history())


def _outside(tmp_path) -> Path:
    target = tmp_path / "outside" / "precious.json"
    target.parent.mkdir()
    target.write_text("precious\n")
    return target


@pytest.mark.parametrize("planted", ["calibration.json", "history/0002.json", "history"])
def test_no_write_through_a_symlink_planted_in_the_state_dir(tmp_path, planted):
    state = tmp_path / "state"
    store = CalibrationStore(state)
    store.save(Calibration(K=np.eye(3) * 50, b=[0, 0, 0], n=1))
    target = _outside(tmp_path)
    link = state / planted
    if link.is_dir():
        for p in link.iterdir():
            p.unlink()
        link.rmdir()
        link.symlink_to(target.parent, target_is_directory=True)
    else:
        link.unlink(missing_ok=True)
        link.symlink_to(target)
    with pytest.raises(InputError, match="symbolic link"):
        CalibrationStore(state).save(Calibration(K=np.eye(3) * 51, b=[0, 0, 0], n=2))
    assert target.read_text() == "precious\n"
    assert sorted(os.listdir(target.parent)) == ["precious.json"]


def test_calibration_save_refuses_a_symlink(tmp_path):
    target = _outside(tmp_path)
    link = tmp_path / "cal.json"
    link.symlink_to(target)
    with pytest.raises(OSError, match="symbolic link"):
        Calibration(K=np.eye(3) * 50, b=[0, 0, 0], n=1).save(link)
    assert target.read_text() == "precious\n"


def test_symlinked_current_file_is_not_read(tmp_path):
    store = CalibrationStore(tmp_path / "state")
    target = tmp_path / "elsewhere.json"
    Calibration(K=np.eye(3) * 50, b=[9, 9, 9], n=42).save(target)
    store.current_path.symlink_to(target)
    result = store.load()
    assert result.calibration is None and "symbolic link" in result.problems[0]


# ------------------------------------------------------------------------ serial commands

def _cal(K, b=(0.0, 0.0, 0.0)):
    return Calibration(K=np.asarray(K, dtype=float), b=b, n=1)


@pytest.mark.parametrize("cal", [
    pytest.param(_cal(np.diag([50.0, -48.0, 52.0])), id="negative_diagonal"),
    pytest.param(_cal([[50.0, 0, 0], [1.0, 48, 0], [0, 0, 52]]), id="not_triangular"),
    pytest.param(_cal(np.diag([50.0, np.nan, 52.0])), id="nan"),
    pytest.param(_cal(np.diag([50.0, 48.0, 52.0]), b=(np.inf, 0, 0)), id="inf_offset"),
    pytest.param(_cal(np.diag([50.0, 48.0, 1e39])), id="beyond_float32"),
])
def test_out_of_range_calibration_is_refused_before_sending(cal):
    port = NullPort()
    link = SerialLink(port, mode="frames")
    with pytest.raises(InputError):
        link.send_calibration(cal, retries=0, timeout=0.01)
    assert bytes(port.written) == b""


@pytest.mark.parametrize("kwargs", [
    {"period_us": -1}, {"period_us": 1 << 32}, {"sums_every": 70_000}, {"sums_every": -1},
    {"outputs": 256}, {"outputs": -1},
])
def test_out_of_range_start_is_refused_before_sending(kwargs):
    port = NullPort()
    link = SerialLink(port, mode="frames")
    try:
        link.start(retries=0, timeout=0.01, **kwargs)
    except StreamcalError as exc:
        assert isinstance(exc, InputError), f"not refused as bad input: {exc!r}"
    except Exception as exc:  # pragma: no cover - what this test is looking for
        pytest.fail(f"start({kwargs}) raised {type(exc).__name__}: {exc} (expected InputError)")
    else:  # pragma: no cover
        pytest.fail(f"start({kwargs}) was accepted")
    assert bytes(port.written) == b""


def test_set_calibration_block_rejects_float32_overflow_on_the_wire():
    """Even if the host let it through, the block's values are finite float32 or the board
    would NAK them: check what from_kb produces for a huge K."""
    block = fr.SetCalibration.from_kb(np.diag([50.0, 48.0, 1e39]), [0, 0, 0])
    assert not np.all(np.isfinite(block.k))   # documents why the host must check the range
