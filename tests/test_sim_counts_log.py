"""Raw AK8963 count logs and mixed-rate tracks through the fake hardware, on simulated data: what
tests/test_daemon_real_mpu9250.py, tests/test_fake_board_counts.py, tests/test_simavr.py and
tests/test_driver.py check on the real recordings.

A simulated hand tumble (µT, body axes) is written as the AK8963 data registers would hold it —
16-bit counts in chip axes, ASA not applied, no accel/gyro/temp, the real logs' metadata — so
the fake serves it unchanged and the driver turns it back into µT in body axes."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import streamcal
from firmware_bridge import registers as R
from firmware_bridge.simavr_board import replay_bytes
from streamcal.inputs.track import Track
from streamcal.sim import simulate

from .conftest import REPO
from .test_daemon_real_mpu9250 import (P, S, check_cli_daemon_on_counts_log,
                                       check_cli_record_of_counts_log,
                                       check_daemon_matches_batch_fit,
                                       check_daemon_with_faults_is_unaffected, to_body)
from .test_driver import check_replay_through_the_driver
from .test_simavr import ASA, _excerpt, _mag_section, _rows

COUNTS_META = {"sensor": "mpu9250 (AK8963 16-bit, 100 Hz)",
               "mag_unit": "counts (nominal 0.15 uT/LSB; ASA not applied)",
               "mag_axes": "AK8963 chip axes (no accelerometer in this log)",
               "origin": "simulated hand tumble (tests/test_sim_counts_log.py)"}


def counts_log(path, seed: int, duration_s: float = 30.0):
    """A simulated tumble as raw counts in chip axes: body = S · P · counts."""
    sim = simulate(duration_s, seed, noise_uT=0.6, mag_rate_hz=100.0, motor=False,
                   temp_profile="constant")
    counts = np.rint(sim.track.mag @ P / S)             # P is orthogonal: P⁻¹ = Pᵀ
    t = sim.track.t_mag - sim.track.t_mag[0]           # the real logs start at 0 s
    Track.from_arrays(t, mag=counts, metadata=COUNTS_META).write(path)
    return path


@pytest.fixture(scope="module", params=[2, 3], ids=["seed2", "seed3"])
def sim_log(request, tmp_path_factory):
    path = counts_log(tmp_path_factory.mktemp("counts") / f"counts_{request.param}.csv",
                      request.param)
    track = Track.read(path)
    assert track.mag_unit == "counts" and not track.has("ax")
    batch = streamcal.fit(track)                   # counts, chip axes
    return path, track, batch, to_body(batch)


def test_daemon_on_a_counts_log_matches_the_batch_fit(sim_log, tmp_path):
    check_daemon_matches_batch_fit(sim_log, tmp_path)


def test_daemon_on_a_counts_log_with_faults_is_unaffected(sim_log, tmp_path):
    check_daemon_with_faults_is_unaffected(sim_log, tmp_path)


def test_cli_daemon_and_record_on_a_counts_log(tmp_path, capsys):
    path = counts_log(tmp_path / "counts.csv", 2)
    check_cli_daemon_on_counts_log(path, tmp_path / "state", capsys)
    check_cli_record_of_counts_log(path, tmp_path / "rec.csv")


def test_record_from_the_fake_board_on_a_counts_log_writes_the_field_in_uT(tmp_path):
    path = counts_log(tmp_path / "counts.csv", 5, duration_s=10.0)
    src = Track.read(path)
    out = tmp_path / "x.csv"
    proc = subprocess.run([sys.executable, "-m", "streamcal", "record", "--port", f"fake:{path}",
                           "-o", str(out)], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    got = Track.read(out)
    assert got.mag_unit == "uT" and len(got) == len(src)
    np.testing.assert_allclose(got.mag, src.mag @ R.AK_TO_BODY.T * (4912.0 / 32760.0),
                               rtol=1e-6, atol=1e-5)
    radius = np.median(np.linalg.norm(got.mag - got.mag.mean(axis=0), axis=1))
    assert 10.0 < radius < 100.0


def test_simavr_replay_file_of_a_counts_log_keeps_its_counts_and_its_asa(tmp_path):
    path = counts_log(tmp_path / "counts.csv", 6, duration_s=8.0)
    src = Track.read(path)
    asa_stated, counts = _mag_section(replay_bytes(src))
    assert asa_stated == (128, 128, 128)
    _, m = _rows(src, ("mx", "my", "mz"))
    np.testing.assert_array_equal(counts[:, 1, :], m)
    lines = path.read_text().splitlines()
    stated = tmp_path / "with_asa.csv"
    stated.write_text("\n".join(lines[:1] + ["# asa: 170,190,160"] + lines[1:400]) + "\n")
    asa_stated, counts = _mag_section(replay_bytes(Track.read(stated)))
    assert asa_stated == (170, 190, 160)
    np.testing.assert_array_equal(counts[:, 1, :], m[:len(counts)])
    assert _mag_section(replay_bytes(_excerpt(1.0)))[0] == ASA


def test_a_mixed_rate_track_replayed_through_the_driver(tmp_path):
    """A simulated track with asynchronous rows (100 Hz mag, 200 Hz IMU, temperature) through
    fake bus + driver + source: every magnetometer sample comes back, each channel within half
    an LSB of the value the chip would hold at that instant."""
    path = tmp_path / "mixed.csv.gz"
    simulate(20.0, 7).track.write(path)
    track = Track.read(path)
    assert not np.any(track.mag_rows & track.accel_rows)
    check_replay_through_the_driver(path)
