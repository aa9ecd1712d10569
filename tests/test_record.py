"""``streamcal record``: tracks recorded from the fake bus and the fake board read back (SPEC §1)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.cli.record import TrackWriter
from streamcal.inputs.track import Track

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "streamcal" / "data" / "demo_track.csv.gz"
# one AK8963 LSB (0.15 µT × fuse-ROM factor ≤ 1.5) and the accel/gyro/temp LSBs of the ranges used
MAG_LSB = 0.15 * 1.5


def record(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "streamcal", "record", *map(str, args)],
                          capture_output=True, text=True, timeout=120, cwd=cwd)


def test_record_from_fake_bus_round_trips(tmp_path):
    out = tmp_path / "rec.csv.gz"
    proc = record("--bus", f"fake:{DEMO}", "-o", out, "--seconds", 30)
    assert proc.returncode == 0, proc.stderr
    got = Track.read(out)
    assert got.metadata["sensor"] == "mpu9250" and "fake i2c" in got.metadata["source"]
    assert got.metadata["streamcal-track"] == "1" and got.mag_unit == "uT"
    orig = Track.read(DEMO)
    ref = orig.select(orig.mag_rows & (orig.t < orig.t[0] + 30))
    # the driver samples at each new magnetometer value: one row per mag sample, IMU alongside
    assert len(got) == len(ref) and got.mag_rows.all()
    np.testing.assert_allclose(got.t, ref.t - ref.t[0], atol=1e-9)
    np.testing.assert_allclose(got.mag, ref.mag, atol=MAG_LSB)
    assert np.all(np.isfinite(got.accel)) and np.all(np.isfinite(got.columns["temp"]))
    assert not list(tmp_path.glob(".*.tmp"))


def test_record_from_fake_board_keeps_rows_as_sampled(tmp_path):
    orig = Track.read(DEMO).select(slice(0, 3000))
    src = tmp_path / "src.csv"
    orig.write(src)
    out = tmp_path / "rec.csv"
    proc = record("--port", f"fake:{src}", "-o", out)
    assert proc.returncode == 0, proc.stderr
    got = Track.read(out)
    assert "serial" in got.metadata["source"]
    # IMU-only rows stay IMU-only: the same empty-cell pattern as the board sent
    assert len(got) == len(orig)
    np.testing.assert_array_equal(got.mag_rows, orig.mag_rows)
    np.testing.assert_array_equal(got.accel_rows, orig.accel_rows)
    np.testing.assert_allclose(got.t, orig.t - orig.t[0], atol=1e-6)
    np.testing.assert_allclose(got.mag, orig.mag, atol=MAG_LSB)


def test_writer_is_atomic_and_continues_time_after_a_board_reboot(tmp_path):
    path = tmp_path / "t.csv"
    w = TrackWriter(path, {"sensor": "mpu9250", "source": "test"})
    n = 5
    mag = np.tile([10.0, 20.0, 30.0], (n, 1))
    w.write(SampleBlock(t=100.0 + 0.01 * np.arange(n), mag=mag, aux={"motor_current": np.ones(n)}))
    assert not path.exists() and Path(w.tmp).exists()   # nothing half-written at the final name
    w.write(SampleBlock(t=0.01 * np.arange(n), mag=mag, aux={"motor_current": np.zeros(n)}))
    w.commit()
    got = Track.read(path)
    assert len(got) == 2 * n and np.all(np.diff(got.t) >= 0) and w.time_resets == 1
    assert got.aux_names == ["motor_current"] and got.columns["motor_current"].sum() == n
    assert not Path(w.tmp).exists()


def test_writer_abort_leaves_nothing(tmp_path):
    w = TrackWriter(tmp_path / "t.csv.gz", {})
    w.write(SampleBlock(t=np.zeros(1), mag=np.ones((1, 3))))
    w.abort()
    assert list(tmp_path.iterdir()) == []


def test_record_refuses_bad_arguments(tmp_path):
    proc = record("--bus", f"fake:{DEMO}", "-o", tmp_path)
    assert proc.returncode == 2 and f"{tmp_path}: is a directory" in proc.stderr
    proc = record("-o", tmp_path / "x.csv")
    assert proc.returncode == 2


@pytest.mark.slow
@pytest.mark.toolchain
def test_record_from_the_firmware_in_simavr_keeps_every_magnetometer_sample(tmp_path):
    """``--port simavr:TRACK``: the compiled sketch samples every 5 ms; every magnetometer row
    of the track arrives once, in order, within half an LSB."""
    from firmware_bridge.simavr_board import missing_toolchain

    if missing_toolchain():
        message = f"simavr toolchain missing: {', '.join(missing_toolchain())} (HARDWARE.md §7)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    orig = Track.read(DEMO)
    orig = orig.select(orig.t < orig.t[0] + 10.0)
    src = tmp_path / "src.csv"
    orig.write(src)
    out = tmp_path / "rec.csv"
    proc = record("--port", f"simavr:{src}", "-o", out)
    assert proc.returncode == 0, proc.stderr
    got = Track.read(out)
    assert "simavr" in got.metadata["source"]
    ref = orig.mag                                    # (N,3) of the rows with mag
    rec = got.mag
    assert len(rec) == len(ref)                       # none skipped by the AK8963, none lost
    np.testing.assert_allclose(rec, ref, atol=MAG_LSB / 2)
    dt = np.diff(got.t)
    assert np.median(dt) == pytest.approx(0.005, abs=1e-5)    # SAMPLE frames every 5 ms
