"""The ``disturbed`` flag of the calibrated-sample JSON lines (streamcal/service/output.py).

A phone passing the board (simulated as in tests/test_stream_disturbance.py: a dipole on a line,
its field exactly zero outside the pass) makes the samples it disturbs disagree with the
calibration in force; the lines of those samples must say ``"disturbed": true``, the others
false. Checked on :meth:`StreamingCalibrator.disagreement` itself, through the service loop
(:class:`streamcal.service.Service`, the daemon's ``_ingest``), and end to end through
``streamcal daemon --bus fake:TRACK`` (the register-level simulated MPU-9250).
"""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.calibration import Calibration
from streamcal.service import Notifier, Outputs, Service, StreamOutput
from streamcal.service.output import format_lines
from streamcal.sim import simulate
from streamcal.stream import CalibrationStore, StreamingCalibrator
from streamcal.inputs.track import Track
from streamcal.stream.disturbance import GROSS
from tests.test_stream_disturbance import B_TRUE, K_TRUE, clean, phone, truth

NOISE_RMS = 0.3        # µT: the stored calibration's rms (the simulated sensor noise is below)
T0, DURATION, PEAK = 30.0, 4.0, 150.0     # the phone: start (s), pass (s), closest field (µT)


def stored_truth(state_dir) -> Calibration:
    """The true calibration saved in ``state_dir``: the calibrator starts with it in force."""
    cal = Calibration(K=K_TRUE, b=B_TRUE, n=1000, rms=NOISE_RMS)
    CalibrationStore(state_dir).save(cal)
    return cal


def relative_error(m, cal: Calibration) -> np.ndarray:
    """(n,) ``|‖K⁻¹(m − b)‖ − 1|``: how far each sample is off the calibration's shell."""
    return np.abs(np.linalg.norm(cal.apply(m), axis=1) - 1.0)


def with_phone(seed: int, duration_s: float = 60.0):
    """(t (M,), m (M,3) µT clean + phone, phone field (M,3)) of a simulated board."""
    t, m = clean(seed, duration_s)
    d = phone(t, T0, DURATION, PEAK, np.random.default_rng(seed))
    return t, m + d, d


class Blocks:
    """A service source over arrays, ``size`` rows a block (the daemon's source adapter API)."""

    description, sleep = "arrays", staticmethod(lambda s: None)

    def __init__(self, t, m, size=50):
        self.t, self.m, self.size, self.i = t, m, size, 0
        self.finished = False

    def read(self):
        if self.i >= len(self.t):
            self.finished = True
            return None
        sl = slice(self.i, self.i + self.size)
        self.i += self.size
        return SampleBlock(t=self.t[sl], mag=self.m[sl])

    def counters(self):
        return {}

    def close(self):
        pass


def parse(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines()]


# ------------------------------------------------------------------- the calibrator's method

def test_disagreement_is_false_before_a_calibration_and_on_missing_rows():
    t, m, _ = with_phone(11)
    sc = StreamingCalibrator(synchronous=True)
    block = SampleBlock(t=t[:300], mag=m[:300])
    sc.ingest(block)
    assert sc.calibration is None
    assert not sc.disagreement(block).any()              # no calibration: never disturbed
    mag = m[2900:3100].copy()                             # the phone's pass, with holes
    mag[::7] = np.nan
    flags = StreamingCalibrator().disagreement(SampleBlock(t=t[2900:3100], mag=mag))
    assert flags.shape == (200,) and flags.dtype == bool and not flags.any()


def test_disagreement_follows_the_hold_back_criterion_and_has_no_side_effects(tmp_path):
    t, m, d = with_phone(12)
    cal = stored_truth(tmp_path)
    sc = StreamingCalibrator(store=CalibrationStore(tmp_path), synchronous=True)
    sc.poll()
    assert sc.calibration is not None
    limit = sc.policy.drift_limit(cal.rms, cal.radius)
    block = SampleBlock(t=t, mag=np.where(np.arange(len(t))[:, None] % 9 == 0, np.nan, m))
    held_before = sc.n_held
    flags = sc.disagreement(block)
    assert sc.n_held == held_before and sc.n_ingested == 0       # nothing judged, nothing staged
    np.testing.assert_array_equal(flags, sc.disagreement(block))  # pure: same answer again
    missing = np.arange(len(t)) % 9 == 0
    assert not flags[missing].any()
    err = relative_error(m, cal)
    quiet = ~np.any(d != 0, axis=1)
    clear = (err > 1.2 * limit) & ~missing
    assert clear.sum() > 20 and flags[clear].all()
    assert flags[quiet & ~missing].mean() < 0.01
    assert not flags[err < 0.8 * limit].any()
    near = np.abs(err - limit) < 1e-9
    np.testing.assert_array_equal(flags[~near & ~missing], (err > limit)[~near & ~missing])


# ------------------------------------------------------------------- through the service loop

@pytest.mark.parametrize("seed", [1, 2])
def test_service_lines_flag_the_phone_burst(tmp_path, seed):
    t, m, d = with_phone(seed)
    cal = stored_truth(tmp_path)
    store = CalibrationStore(tmp_path)
    made = []

    def no_refit(snapshot):         # the stored calibration stays in force all along
        raise RuntimeError("refits are off in this test")

    def make(buffer=None):
        made.append(StreamingCalibrator(store=store, synchronous=True, fitter=no_refit))
        return made[-1]

    stream = io.StringIO()
    service = Service(make, Blocks(t, m), outputs=Outputs([StreamOutput(stream)]),
                      notifier=Notifier(environ={}), log=lambda line: None)
    service.run()
    rows = parse(stream.getvalue())
    assert rows and all(list(r)[-1] == "disturbed" for r in rows)   # the key comes last
    assert all(isinstance(r["disturbed"], bool) for r in rows)
    kinds = service.stats.events
    assert kinds.get("disturbance", 0) >= 1 and "drift" not in kinds and "accepted" not in kinds
    by_t = {round(r["t"], 6): r["disturbed"] for r in rows}
    assert len(by_t) == len(t)                                        # one line per sample
    flags = np.array([by_t[round(x, 6)] for x in t])
    err = relative_error(m, cal)
    limit = made[-1].policy.drift_limit(cal.rms, cal.radius)
    burst = np.any(d != 0, axis=1)
    clear = burst & (err > 1.2 * limit)
    assert clear.sum() > 20 and flags[clear].all(), "a clearly disturbed sample is not flagged"
    # Without the phone only the sensor noise's rare crossings of the limit remain.
    assert flags[~burst].mean() < 0.002, "samples without the phone flagged"
    # The stored calibration covers every direction: the criterion is the limit on all of them.
    near = np.abs(err - limit) < 1e-9
    np.testing.assert_array_equal(flags[~near], (err > limit)[~near])
    # The lines flag exactly what the calibrator held back (same criterion, same calibration).
    assert int(flags.sum()) == made[-1].n_held


def test_streamed_calibration_then_phone_lines_are_flagged():
    """No stored calibration: the calibrator's own first fit is in force when the phone passes."""
    t, m = clean(3)
    rng = np.random.default_rng(3)
    t0, duration = 100.0, 4.0
    d = phone(t, t0, duration, 150.0, rng)
    stream = io.StringIO()
    service = Service(lambda buffer=None: StreamingCalibrator(synchronous=True), Blocks(t, m + d),
                      outputs=Outputs([StreamOutput(stream)]), notifier=Notifier(environ={}),
                      log=lambda line: None)
    service.run()
    rows = parse(stream.getvalue())
    first_cal = min(r["t"] for r in rows if r["cal_version"] >= 1)
    assert first_cal < t0 and not any(r["disturbed"] for r in rows if r["cal_version"] == 0)
    by_t = {round(r["t"], 6): r["disturbed"] for r in rows}
    flags = np.array([by_t.get(round(x, 6), False) for x in t])
    burst = np.any(d != 0, axis=1)
    calibrated = t > first_cal + 5.0
    # A streamed fit judges by the drift limit the directions it was fitted on, by GROSS (half
    # the field) every direction.
    gross = burst & calibrated & (relative_error(m + d, truth()) > GROSS + 0.1)
    assert gross.sum() > 20 and flags[gross].all()
    assert flags[burst].sum() > gross.sum()
    assert flags[~burst & calibrated].mean() < 0.01


# ------------------------------------------------------------------- format_lines

def test_format_lines_adds_the_flag_last_and_keeps_the_rest():
    t = [0.0, 0.1, 0.2, 0.3]
    field = [[1.0, 0, 0], [np.nan] * 3, [0.0, 3.0, 4.0], [0.0, 0.0, 2.0]]
    rows = parse(format_lines(t, field, 2, [True, True, False, True]))
    assert [r["t"] for r in rows] == [0.0, 0.2, 0.3]          # the NaN row is skipped, flag too
    assert [r["disturbed"] for r in rows] == [True, False, True]
    assert list(rows[1]) == ["t", "field_uT", "direction", "cal_version", "disturbed"]
    assert rows[1]["direction"] == [0.0, 0.6, 0.8] and rows[1]["cal_version"] == 2
    assert [r["disturbed"] for r in parse(format_lines(t, field, 0))] == [False] * 3
    with pytest.raises(ValueError):
        format_lines(t, field, 1, [True])


# ------------------------------------------------------------------- the daemon, end to end

def test_daemon_over_fake_bus_lines_carry_the_flag(tmp_path, capsys):
    from tests.test_daemon import run_cli_in_process

    seed = 21
    tr = simulate(60.0, seed=seed, K=K_TRUE, b=B_TRUE, outlier_bursts=0, motor=False,
                  imu_rate_hz=100.0, temp_profile="constant").track
    rows = tr.mag_rows
    d_mag = phone(tr.t_mag, T0, DURATION, PEAK, np.random.default_rng(seed))
    cols = {name: np.array(col, dtype=float) for name, col in tr.columns.items()}
    for k, name in enumerate(("mx", "my", "mz")):
        cols[name][rows] += d_mag[:, k]
    path = tmp_path / "phone.csv"
    Track(cols, tr.metadata).write(path)
    state = tmp_path / "state"
    cal = stored_truth(state)
    code, out, err = run_cli_in_process(
        ["daemon", "--bus", f"fake:{path}", "--state-dir", str(state), "--no-socket",
         "--sync-fits", "--json-lines"], capsys)
    assert code == 0, err
    lines = [json.loads(line) for line in out.splitlines() if line.startswith('{"t"')]
    assert len(lines) > 0.9 * rows.sum()
    assert all(list(r) == ["t", "field_uT", "direction", "cal_version", "disturbed"]
               for r in lines)
    t_line = np.array([r["t"] for r in lines])
    flags = np.array([r["disturbed"] for r in lines])
    # Lines in time order with the track's clock: look up the phone's field at each line.
    idx = np.clip(np.searchsorted(tr.t_mag, t_line - 1e-4), 0, len(tr.t_mag) - 1)
    assert np.abs(tr.t_mag[idx] - t_line).max() < 5e-3
    d = d_mag[idx]
    burst = np.any(d != 0, axis=1)
    # The daemon refits as coverage grows: a refit judges by the drift limit only the
    # directions it was fitted on, and by GROSS (half the field) everywhere.
    gross = burst & (relative_error(tr.mag[idx] + d, cal) > GROSS + 0.1)
    assert gross.sum() > 20 and flags[gross].all()
    assert flags[burst].sum() > gross.sum()                  # and more by the drift limit
    assert flags[~burst].mean() < 0.002
