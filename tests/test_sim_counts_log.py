"""Raw AK8963 count logs and mixed-rate tracks through the fake hardware, on simulated data: what
tests/test_daemon_real_mpu9250.py, tests/test_fake_board_counts.py, tests/test_simavr.py and
tests/test_driver.py check on the real recordings.

A simulated hand tumble (µT, body axes) is written as the AK8963 data registers would hold it —
16-bit counts in chip axes, ASA not applied, no accel/gyro/temp, the real logs' metadata — so
the fake serves it unchanged and the driver turns it back into µT in body axes."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import streamcal
from firmware_bridge import registers as R
from firmware_bridge.fake_mpu9250 import Faults
from firmware_bridge.i2c_source import open_i2c_source
from firmware_bridge.simavr_board import replay_bytes
from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.inputs.track import Track
from streamcal.sim import simulate

from .conftest import REPO
from .test_daemon_real_mpu9250 import P, S, SIGMA_CAP, run_daemon, sampling_error, to_body
from .test_driver import bounds
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
    path, track, batch, reference = sim_log
    service, stored, log = run_daemon(path, tmp_path)
    assert stored.unit == "uT" and batch.unit != "uT"
    assert service.summary()["samples"] == len(track.t_mag)
    assert any("at rest" in line and "raw AK8963 counts" in line for line in log)
    sigma = sampling_error(track.mag, stored.n, reference)
    assert sigma < SIGMA_CAP
    assert stored.model_error(reference) < 2 * sigma
    assert stored.model_error(batch.replace(unit="uT")) > 0.5   # the mapping matters


def test_daemon_on_a_counts_log_with_faults_is_unaffected(sim_log, tmp_path):
    path, track, _, reference = sim_log
    t0, t1 = float(track.t[0]), float(track.t[-1])
    start = t0 + 0.4 * (t1 - t0)
    faults = Faults(nack_rate=0.03, vanish=[(start, start + 2.0)],
                    self_resets=[(t0 + 0.6 * (t1 - t0), "both")])
    service, stored, log = run_daemon(path, tmp_path, faults)
    counters = service.source.counters()
    assert counters["nacks"] > 0 and counters["reinits"] >= 2
    assert service.stats.outages >= 1 and any("device answers again" in line for line in log)
    assert service.stats.ingest_errors == 0
    assert 0 < service.stats.samples < len(track.t_mag)
    sigma = sampling_error(track.mag, stored.n, reference)
    assert stored.model_error(reference) < 2 * sigma


def test_cli_daemon_and_record_on_a_counts_log(tmp_path, capsys):
    path = counts_log(tmp_path / "counts.csv", 2)
    state = tmp_path / "state"
    code = main(["daemon", "--bus", f"fake:{path}", "--state-dir", str(state), "--no-socket",
                 "--sync-fits"])
    out, err = capsys.readouterr()
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["samples"] == len(Track.read(path).t_mag) and summary["cal_version"] >= 1
    assert Calibration.load(state / "calibration.json").unit == "uT"
    assert "Traceback" not in err
    rec = tmp_path / "rec.csv"
    assert main(["record", "--bus", f"fake:{path}", "-o", str(rec)]) == 0
    got, src = Track.read(rec), Track.read(path)
    assert got.mag_unit == "uT" and "at rest" in got.metadata["source"]
    np.testing.assert_allclose(got.mag, S * src.mag @ P.T, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.t_mag, src.t_mag)


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
    src = open_i2c_source(f"fake:{path}", block_size=500, read_track=Track.read)
    blocks = list(src)
    d = src.driver
    t = np.concatenate([b.t for b in blocks])
    np.testing.assert_array_equal(t, track.t_mag)
    bm, ba, bg, bt = bounds(d)
    mag = np.concatenate([b.mag for b in blocks])
    assert np.all(np.abs(mag - track.mag) <= bm)
    for name, rows, values, bound in (("accel", track.accel_rows, track.accel, ba),
                                      ("gyro", track.gyro_rows, track.gyro, bg)):
        k = np.searchsorted(track.t[rows], t, side="right") - 1
        got = np.concatenate([getattr(b, name) for b in blocks])
        assert np.all(np.abs(got[k >= 0] - values[k[k >= 0]]) <= bound)
    temp_rows = np.isfinite(track.columns["temp"])
    k = np.searchsorted(track.t[temp_rows], t, side="right") - 1
    got = np.concatenate([b.temp for b in blocks])
    assert np.all(np.abs(got[k >= 0] - track.columns["temp"][temp_rows][k[k >= 0]]) <= bt)
    assert d.bus.violations == [] and d.stats["retries"] == 0
