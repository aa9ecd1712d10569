"""Logs of a crash or a power cut (cut inside a message, damaged in the middle) and batch over
every input format: never a traceback; exit 0 with one line saying what was lost, or exit 2
with one line when nothing usable remains."""
import contextlib
import io

import numpy as np
import pytest

from streamcal.batching import batch
from streamcal.cli import main
from streamcal.inputs import read_recording
from streamcal.inputs.track import Track

from ._dataflash_log import write_flight

KB = 1024


@pytest.fixture(scope="module")
def small_bin(tmp_path_factory):
    path = tmp_path_factory.mktemp("crash") / "flight.bin"
    write_flight(path, [{"ofs": (1.0, 2.0, 3.0)}, {"ofs": (4.0, 5.0, 6.0)}], seconds=30)
    return path


def _convert(path, out):
    """(exit code, non-empty stderr lines) of ``streamcal convert``; an exception escapes."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["convert", str(path), "-o", str(out)])
    return code, [line for line in err.getvalue().splitlines() if line.strip()]


def _fuzz(data: bytes, tmp_path, suffix: str, seed: int) -> dict:
    """Cut at every 1 kB of the first 50 kB, each cut also with 20 flipped bytes."""
    rng = np.random.default_rng(seed)
    seen = {0: 0, 2: 0}
    for kb in range(1, 51):
        for flip in (False, True):
            blob = bytearray(data[:kb * KB])
            if flip:
                for at in rng.integers(0, len(blob), 20):
                    blob[at] ^= int(rng.integers(1, 256))
            path = tmp_path / f"cut{kb}{'f' if flip else ''}{suffix}"
            path.write_bytes(bytes(blob))
            code, lines = _convert(path, tmp_path / "out.csv")
            assert code in (0, 2), (path, code, lines)
            assert len(lines) <= 1, (path, lines)
            if code == 0:   # one line exactly when something was lost
                warned = Track.read(tmp_path / "out.csv").metadata.get("read_warnings")
                assert len(lines) == (1 if warned else 0), (path, lines, warned)
            if lines:
                assert str(path) in lines[0], (path, code, lines)
            seen[code] += 1
    return seen


@pytest.mark.filterwarnings("error::RuntimeWarning")   # a warning is a second line
def test_dataflash_fuzz_never_a_traceback(small_bin, tmp_path):
    data = small_bin.read_bytes()
    assert len(data) > 50 * KB
    seen = _fuzz(data, tmp_path, ".bin", seed=1)
    assert seen[0] > 50 and seen[2] > 0    # most cuts still hold MAG; the first ones none


@pytest.mark.filterwarnings("error::RuntimeWarning")   # a warning is a second line
def test_ulog_fuzz_never_a_traceback(flight_dir, tmp_path):
    seen = _fuzz((flight_dir / "px4_pyulog_sample.ulg").read_bytes(), tmp_path, ".ulg", seed=2)
    assert seen[0] > 0


def test_cut_log_counts_what_was_lost(small_bin, tmp_path):
    """Cut 5 bytes into a message: the complete messages are kept, the 5 bytes named."""
    data = small_bin.read_bytes()
    whole = read_recording(small_bin, compass=1)
    at = data.rfind(b"\xa3\x95", 0, len(data) // 2)
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[:at + 5])
    track = read_recording(cut, compass=1)
    assert "truncated: 5 trailing bytes ignored" in track.metadata["read_warnings"]
    n = len(track.t_mag)
    assert 0.4 * len(whole.t_mag) < n < 0.6 * len(whole.t_mag)
    np.testing.assert_array_equal(track.mag, whole.mag[:n])


def test_damaged_middle_skipped_and_counted(small_bin, tmp_path):
    """Random bytes written over the middle of the log: reading resumes at the next valid
    message header and the skipped bytes are counted."""
    data = bytearray(small_bin.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 300] = np.random.default_rng(3).integers(0, 256, 300, dtype=np.uint8).tobytes()
    bad = tmp_path / "damaged.bin"
    bad.write_bytes(bytes(data))
    track = read_recording(bad)
    whole = read_recording(small_bin)
    assert "Skipped" in track.metadata["read_warnings"]
    assert len(whole.t_mag) - 10 < len(track.t_mag) < len(whole.t_mag)
    code, lines = _convert(bad, tmp_path / "o.csv")
    assert code == 0 and len(lines) == 1 and "bad bytes" in lines[0]


def test_batch_reads_logs_and_says_what_a_cut_lost(small_bin, tmp_path):
    """batch over a DataFlash log and a cut copy (not UTF-8 text): both read like the other
    commands read them, the cut one's loss in first_skipped, --compass honoured."""
    cut = tmp_path / "cut.bin"
    data = small_bin.read_bytes()
    cut.write_bytes(data[:len(data) * 3 // 4 + 7])
    rows = batch([small_bin, cut], "diagnose", jobs=1, compass=1)
    assert [r["status"] for r in rows] == ["ok", "ok"], rows
    assert rows[0]["first_skipped"] is None
    assert "truncated" in rows[1]["first_skipped"]
    assert rows[1]["n"] < rows[0]["n"]
    out = tmp_path / "summary.csv"
    assert main(["batch", "fit", str(small_bin), "--compass", "1", "--jobs", "1", "-o",
                 str(out)]) in (0, 1)
    assert "not UTF-8" not in out.read_text()


@pytest.mark.filterwarnings("error::RuntimeWarning")   # a warning is a second line
def test_self_made_ulog_fuzz_never_a_traceback(tmp_path):
    from ._ulog_log import write_ulog

    path = tmp_path / "two.ulg"
    write_ulog(path, [(0.05, -0.1, 0.02), (-0.2, 0.1, 0.3)], seconds=40)
    data = path.read_bytes()
    assert len(data) > 50 * KB
    seen = _fuzz(data, tmp_path, ".ulg", seed=4)
    assert seen[0] > 40


def test_ulog_damaged_middle_skipped_and_counted(tmp_path):
    from ._ulog_log import write_ulog

    path = tmp_path / "ok.ulg"
    write_ulog(path, [(0.05, -0.1, 0.02)], seconds=40)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 300] = np.random.default_rng(5).integers(0, 256, 300, dtype=np.uint8).tobytes()
    bad = tmp_path / "damaged.ulg"
    bad.write_bytes(bytes(data))
    whole, track = read_recording(path), read_recording(bad)
    warning = track.metadata["read_warnings"]
    assert "Skipped damaged data" in warning and "bytes in" in warning, warning
    assert 0.9 * len(whole.t_mag) < len(track.t_mag) < len(whole.t_mag)
    code, lines = _convert(bad, tmp_path / "o.csv")
    assert code == 0 and len(lines) == 1 and "Skipped damaged data" in lines[0]


def test_ulog_without_sync_read_past_the_damage(tmp_path):
    """A ULog without sync messages (tests/_selfmade_logs.py writes none) with random bytes in
    the middle: reading resumes at the next valid message, every sample after the damage is
    read, and the one line counts the bytes cut out (those of the damaged messages)."""
    from ._selfmade_logs import flight_slice, ulog_bytes

    data = ulog_bytes(flight_slice(40.0))
    assert b"\x2f\x73\x13\x20\x25\x0c\xbb\x12" not in data
    path = tmp_path / "ok.ulg"
    path.write_bytes(data)
    whole = read_recording(path)
    damaged = bytearray(data)
    mid = len(data) // 2
    damaged[mid:mid + 300] = np.random.default_rng(7).integers(0, 256, 300,
                                                               dtype=np.uint8).tobytes()
    bad = tmp_path / "damaged.ulg"
    bad.write_bytes(bytes(damaged))
    track = read_recording(bad)
    # every magnetometer sample after the damage is there, with its values
    t_end = whole.t_mag[-1]
    assert track.t_mag[-1] == t_end
    after = whole.t_mag > whole.t_mag[len(whole.t_mag) // 2] + 1.0
    kept = np.isin(whole.t_mag, track.t_mag)
    assert kept[after].all() and len(whole.t_mag) - 10 < len(track.t_mag) < len(whole.t_mag)
    np.testing.assert_array_equal(track.mag, whole.mag[kept])
    warning = track.metadata["read_warnings"]
    lost = int(warning.split("Skipped damaged data: ")[1].split(" bytes")[0])
    assert 300 <= lost < 300 + 2 * 120, warning      # the damage and the messages it cut into
    assert "truncated" not in warning
    code, lines = _convert(bad, tmp_path / "o.csv")
    assert code == 0 and len(lines) == 1 and "Skipped damaged data" in lines[0]
