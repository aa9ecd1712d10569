"""Transient disturbances versus environment changes in the streaming calibrator.

A phone passing the board (a few seconds of 100–200 µT, the sensor unchanged) must not make the
calibrator forget its buffer: the samples it disturbs are held back and one ``disturbance`` event
reports it. A new hard iron (a magnet stuck to the board) must still be detected as an environment
change (``drift`` → ``forgot`` → a new calibration), and a disturbance that lasts (a motor left
running next to the board) becomes one too, with the old calibration recalled when it stops.
Simulated boards (``streamcal.sim``), several seeds; the phone is a dipole moving past on a line.
"""
from functools import lru_cache

import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.calibration import Calibration
from streamcal.sim import simulate
from streamcal.stream import StreamingCalibrator
from streamcal.stream.disturbance import GROSS, Quarantine, shell_fit

K_TRUE = np.array([[46.0, 0.9, -1.2], [0.0, 44.5, 0.7], [0.0, 0.0, 49.5]])
B_TRUE = np.array([10.0, -6.0, 3.0])
BOUND = 0.01          # model error of a good streaming fit (tests/test_reliability_environment.py)


@lru_cache(maxsize=None)
def clean(seed: int, duration: float = 150.0, b: tuple = tuple(B_TRUE)):
    """(t (M,), m (M,3) µT) of a simulated board turned by hand, no disturbance."""
    tr = simulate(duration, seed=seed, K=K_TRUE, b=np.array(b), outlier_bursts=0, motor=False,
                  imu_rate_hz=100.0, temp_profile="constant").track
    return np.asarray(tr.t_mag, dtype=float), np.asarray(tr.mag, dtype=float)


def phone(t, t0: float, duration: float, peak_uT: float, rng) -> np.ndarray:
    """(M,3) µT: a dipole passing the board on a straight line during [t0, t0 + duration]; its
    1/r³ field rises and falls, ``peak_uT`` at closest approach, exactly zero outside."""
    moment = rng.standard_normal(3)
    normal = rng.standard_normal(3)
    normal /= np.linalg.norm(normal)
    velocity = np.cross(normal, rng.standard_normal(3))
    velocity /= np.linalg.norm(velocity)
    s = (t - (t0 + duration / 2)) / (duration / 2) * 4.6          # ±4.6 closest distances
    pos = normal + s[:, None] * velocity
    r = np.linalg.norm(pos, axis=1, keepdims=True)
    rhat = pos / r
    field = (3 * (rhat @ moment)[:, None] * rhat - moment) / r ** 3
    field[(t < t0) | (t > t0 + duration)] = 0.0
    return field * peak_uT / np.linalg.norm(field, axis=1).max()


def feed(sc, t, m, block=50):
    events = []
    for i in range(0, len(t), block):
        events += sc.ingest(SampleBlock(t=t[i:i + block], mag=m[i:i + block]))
    return events + sc.close()


def of_kind(events, kind):
    return [e for e in events if e.kind == kind]


def truth(b=B_TRUE):
    return Calibration(K=K_TRUE, b=np.asarray(b), n=1)


# ------------------------------------------------------------------------- the shell test

def test_shell_fit_finds_a_moved_unit_sphere_and_refuses_a_phone_path():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((300, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    c_true = np.array([0.4, -0.3, 0.2])
    c, res = shell_fit(x + c_true + rng.normal(scale=0.005, size=x.shape))
    np.testing.assert_allclose(c, c_true, atol=0.01)
    assert np.median(res) < 0.01
    # A board at rest with a magnet: one cluster, explained by the smallest offset.
    y = np.array([0.0, 0.0, 1.6]) + rng.normal(scale=0.005, size=(200, 3))
    c, res = shell_fit(y)
    assert np.median(res) < 0.01 and np.linalg.norm(c) == pytest.approx(0.6, abs=0.02)
    # A phone passing a board at rest: the field goes out to 3× and back along a curve.
    s = np.linspace(-1, 1, 200)[:, None]
    y = np.array([0.0, 0.0, 1.0]) + 3.0 * (1 - s ** 2) * np.array([[0.6, 0.8, 0.0]]) \
        + 0.8 * s * np.array([[0.0, 0.0, 1.0]])
    assert np.median(shell_fit(y)[1]) > 0.1


def test_quarantine_is_a_bounded_ring():
    q = Quarantine(capacity=8, n_covariates=1)
    for k in range(3):
        t = np.arange(5.0) + 5 * k
        q.push(np.ones((5, 3)) * t[:, None], np.zeros((5, 3)), t, t[:, None])
    assert q.n_held == 15 and q.m.shape == (8, 3)
    idx = q.since(9.0)
    np.testing.assert_array_equal(q.t[idx], np.arange(9.0, 15.0))
    np.testing.assert_array_equal(q.cov[idx, 0], np.arange(9.0, 15.0))
    q.clear()
    assert not len(q.since(-1e9))


# ---------------------------------------------------------------------- a passing phone

@pytest.mark.parametrize("seed", [1, 2, 3])
def test_passing_phone_is_one_disturbance_and_the_buffer_is_kept(seed):
    t, m = clean(seed)
    rng = np.random.default_rng(seed)
    t0, duration = 100.0, rng.uniform(2.0, 5.0)
    d = phone(t, t0, duration, rng.uniform(100.0, 200.0), rng)
    sc = StreamingCalibrator(synchronous=True)
    before = t < t0
    events = feed(sc, t[before], m[before])
    assert sc.calibration is not None and not sc.stale, "no calibration before the phone"
    cells_before = sc.buffer.fraction
    events = feed(sc, t[~before], m[~before] + d[~before])
    kinds = [e.kind for e in events]
    assert "drift" not in kinds and "forgot" not in kinds and "recalled" not in kinds
    (dist,) = of_kind(events, "disturbance")
    assert t0 - 0.5 <= dist.data["start"] <= t0 + duration
    assert t0 + 0.5 * duration <= dist.data["end"] <= t0 + duration + 5.0
    peak = np.linalg.norm(d, axis=1).max()
    assert 0.5 * peak <= dist.data["peak"] <= 1.5 * peak          # µT, against the phone's field
    assert dist.data["held"] > 0 and sc.n_held >= dist.data["held"]
    # Coverage kept; of the samples the phone disturbed by more than half the field, only
    # those its field happened to carry across the shell (they look clean) entered the buffer.
    assert sc.buffer.fraction >= cells_before
    snap = sc.buffer.snapshot()
    assert snap.t.min() < t0                                    # old samples still there
    gross = np.linalg.norm(d, axis=1) > GROSS * 44.5
    stored = np.isin(t, snap.t)
    assert (gross & stored).sum() <= 0.05 * gross.sum()
    assert sc.calibration.model_error(truth()) < BOUND
    assert not sc.stale


# ------------------------------------------------------------- a real environment change

@pytest.mark.parametrize("seed", [4, 5])
def test_new_hard_iron_is_an_environment_change(seed):
    b_after = B_TRUE + np.array([25.0, 18.0, -20.0])          # ≈ 36 µT: a magnet on the board
    t1, m1 = clean(seed, 120.0)
    t2, m2 = clean(seed + 100, 150.0, tuple(b_after))
    t2 = t2 + 120.0
    sc = StreamingCalibrator(synchronous=True)
    events = feed(sc, t1, m1)
    assert sc.calibration is not None
    events = feed(sc, t2, m2)
    kinds = [e.kind for e in events]
    assert "disturbance" not in kinds[:kinds.index("drift")] if "drift" in kinds else False
    drift = of_kind(events, "drift")[0]
    assert drift.data["reason"] == "new_shell"
    assert 120.0 <= drift.data["onset"] and drift.t <= 120.0 + 30.0
    forgot = of_kind(events, "forgot")[0]
    assert forgot.t == drift.t and forgot.data["dropped"] > 0
    assert forgot.data["held_added"] > 0           # the held samples were the new field's
    assert sc.buffer.snapshot().t.min() >= drift.data["onset"]
    assert [e for e in of_kind(events, "accepted") if e.t > drift.t]
    assert sc.calibration.model_error(truth(b_after)) < BOUND and not sc.stale


def test_a_lasting_disturbance_becomes_a_change_and_the_calibration_is_recalled():
    """A motor running next to the board for 40 s: its field swings, so it lies on no shell,
    but it lasts; when it stops the remembered calibration fits again."""
    t, m = clean(6, 160.0)
    on = (t >= 100.0) & (t < 140.0)
    swing = np.zeros_like(m)
    swing[on] = 60.0 * np.sin(2 * np.pi * 0.7 * t[on])[:, None] * np.array([0.6, -0.48, 0.64])
    sc = StreamingCalibrator(synchronous=True)
    before = t < 100.0
    feed(sc, t[before], m[before])
    first = sc.calibration
    assert first is not None
    events = feed(sc, t[~before], m[~before] + swing[~before])
    drift = of_kind(events, "drift")
    assert len(drift) == 1 and drift[0].data["reason"] == "persisted"
    rule = sc.disturbance_rule
    assert 100.0 + rule.persist_s <= drift[0].t <= 100.0 + rule.persist_s + 3.0
    # Recall needs ``recall_checks`` consecutive fitting windows, judged once per stage of 256
    # rows (2.56 s at 100 Hz).
    recalled = of_kind(events, "recalled")
    assert recalled and 140.0 <= recalled[0].t <= 140.0 + (sc.recall_checks + 1) * 2.56
    assert not sc.stale and sc.calibration.model_error(first) < BOUND


# -------------------------------------------------------- before the first calibration

def cap_spiral(t, b, cap_deg=60.0, seed=0):
    """(M,3) µT: a board turned over a cap of directions (not enough for a first fit)."""
    th = np.radians(cap_deg) * (0.5 - 0.5 * np.cos(2 * np.pi * t / 20.0))
    ph = 2 * np.pi * t / 3.0
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    return 48.0 * d + b + np.random.default_rng(seed).normal(scale=0.3, size=d.shape)


@pytest.mark.parametrize("seed", [0, 1])
def test_change_before_the_first_calibration_splits_the_environments(seed):
    """No calibration yet (every fit refused): the running sphere estimate is the reference,
    and a new hard iron makes the calibrator forget the old environment's samples instead of
    mixing both shells."""
    from streamcal.errors import InsufficientDataError

    def refuse(snap):
        raise InsufficientDataError("not enough directions")

    t = np.arange(0.0, 80.0, 0.01)
    b2 = B_TRUE + np.array([20.0, -15.0, 12.0])
    m = np.where((t < 40.0)[:, None], cap_spiral(t, B_TRUE, seed=seed),
                 cap_spiral(t, b2, seed=seed + 10))
    sc = StreamingCalibrator(fitter=refuse, synchronous=True)
    events = feed(sc, t, m)
    drift = of_kind(events, "drift")
    assert len(drift) == 1 and not drift[0].data["calibrated"]
    assert drift[0].data["reason"] == "new_shell"
    assert 40.0 <= drift[0].data["onset"] and drift[0].t <= 40.0 + 10.0
    forgot = of_kind(events, "forgot")[0]
    assert forgot.data["dropped"] > 0 and not sc.stale
    assert sc.buffer.snapshot().t.min() >= drift[0].data["onset"]
    envs = sc.environment_summary()
    assert len(envs) == 2 and envs[0]["end"] == drift[0].data["onset"]
    assert all(0.0 < e["coverage"] < 0.35 for e in envs)
    # The running estimate is now the new environment's sphere.
    c, R = sc.coarse
    assert np.linalg.norm(c - b2) < 3.0 and abs(R - 48.0) < 3.0


def test_replay_says_why_there_is_no_calibration(tmp_path, capsys):
    from streamcal.cli import main
    from streamcal.inputs.track import Track

    t = np.arange(0.0, 80.0, 0.01)
    b2 = B_TRUE + np.array([20.0, -15.0, 12.0])
    m = np.where((t < 40.0)[:, None], cap_spiral(t, B_TRUE), cap_spiral(t, b2, seed=10))
    path = tmp_path / "two.csv"
    Track.from_arrays(t, mag=m).write(path)
    code = main(["replay", str(path), "--sync-fits"])
    err = capsys.readouterr().err
    assert code == 1
    assert "no calibration" in err and "the field changed 1 time(s)" in err
    assert "coverage per environment: t=0.0–" in err


# ------------------------------------------- a small permanent change (one or two limits)

@pytest.mark.parametrize("seed,scale", [(1, 1.5), (2, 1.5), (1, 2.0), (3, 1.2)])
def test_small_permanent_change_is_no_transient(seed, scale):
    """A new hard iron of 1–2 drift limits moves the window median little: most directions
    still agree. It must end as an environment change or be absorbed by the refits — never as
    a series of "transient" disturbances ended by accepting refits of the old samples."""
    t, m = clean(seed, 300.0)
    sc = StreamingCalibrator(synchronous=True)
    before = t < 120.0
    feed(sc, t[before], m[before])
    assert sc.calibration is not None and not sc.stale
    limit = sc.drift_limit
    c = np.array([1.0, 0.5, -0.3])
    delta = K_TRUE @ (scale * limit * c / np.linalg.norm(c))      # µT
    events = feed(sc, t[~before], m[~before] + delta)
    assert not [e for e in of_kind(events, "disturbance") if e.data["outcome"] == "transient"]
    # No acceptance while a disturbance is open: none between a disturbance's start and its
    # decision (a drift event).
    for d in of_kind(events, "drift"):
        assert not [e for e in of_kind(events, "accepted") if d.data["onset"] <= e.t < d.t]
    assert len(of_kind(events, "drift")) <= 1
    assert sc.calibration.model_error(truth(B_TRUE + delta)) < BOUND and not sc.stale


def test_disturbance_open_at_close_is_reported_undecided():
    t, m = clean(1)
    sc = StreamingCalibrator(synchronous=True)
    before = t < 100.0
    feed(sc, t[before], m[before])
    end = (t >= 100.0) & (t < 103.0)            # the stream ends while a magnet is near
    magnet = np.array([15.0, -10.0, 8.0])
    events = feed(sc, t[end], m[end] + magnet)
    (dist,) = of_kind(events, "disturbance")
    assert dist.data["open"] and dist.data["outcome"] == "open"
    assert "transient" not in dist.message and "still open" in dist.message
    assert not of_kind(events, "drift")


def test_rows_without_the_covariates_the_calibration_needs_are_not_judged(tmp_path):
    """A calibration with a temperature term, and blocks without a temperature: its effect
    terms cannot be evaluated there, so those rows are buffered but neither judged nor held."""
    from streamcal.stream import CalibrationStore, CoverageBuffer

    cal = Calibration(K=K_TRUE, b=B_TRUE, model=("hard_iron", "soft_iron", "temperature_offset"),
                      effects={"temperature_offset": {"T0": 25.0, "c": [0.05, 0.0, 0.0]}},
                      rms=0.4, n=1000)
    CalibrationStore(tmp_path).save(cal)
    sc = StreamingCalibrator(store=CalibrationStore(tmp_path), synchronous=True,
                             buffer=CoverageBuffer(covariates=("temp",)),
                             fitter=lambda snap: cal)
    assert sc.calibration is not None
    t, m = clean(2, 40.0)
    magnet = np.array([15.0, -10.0, 8.0])
    events = feed(sc, t, m + magnet)            # no temperature column: nothing can be judged
    assert sc.n_held == 0 and not of_kind(events, "drift")
    assert sc.buffer.n_samples > 0
    # With a temperature, the same field disagrees and is held back.
    sc = StreamingCalibrator(store=CalibrationStore(tmp_path), synchronous=True,
                             buffer=CoverageBuffer(covariates=("temp",)),
                             fitter=lambda snap: cal)
    for i in range(0, len(t), 50):
        sc.ingest(SampleBlock(t=t[i:i + 50], mag=m[i:i + 50] + magnet,
                              temp=np.full(len(t[i:i + 50]), 25.0)))
    assert sc.n_held > 0


def test_new_shell_needs_at_least_four_samples():
    from streamcal.stream.disturbance import Disturbance, DisturbanceRule

    rule = DisturbanceRule(min_held=0, min_age_s=0.0)
    ok, center, shell = rule.new_shell(Disturbance(0.0), np.zeros((0, 3)), 0.03, 10.0)
    assert not ok and center is None
    y = np.array([[0.0, 0.0, 1.2], [0.0, 1.2, 0.0], [1.2, 0.0, 0.0], [0.0, 0.0, -0.8],
                  [0.0, -0.8, 0.0]])
    ok, center, shell = rule.new_shell(Disturbance(0.0), y, 0.03, 10.0)
    assert center is not None and np.isfinite(shell)


def _hemisphere(rng, n, sign):
    x = rng.standard_normal((n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    x[:, 2] = sign * np.abs(x[:, 2])
    return x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_disturbance_the_window_cannot_judge_does_not_block_fitting(seed):
    """Calibrated on the upper half of the sphere; a phone passes; then the board turns only
    through the lower half, where the drift window does not look (directions the calibration
    was not fitted on). The fit that finished during the phone waits at most the persistence
    time for a decision, then the disturbance is reported undecided and fitting goes on —
    no false environment change, and the lower half is learnt."""
    rng = np.random.default_rng(seed)
    fs, n_up, n_phone, n_down = 100.0, 6000, 500, 4000
    x = np.vstack([_hemisphere(rng, n_up + n_phone, +1), _hemisphere(rng, n_down, -1)])
    t = np.arange(len(x)) / fs
    m = x @ K_TRUE.T + B_TRUE + rng.normal(scale=0.3, size=x.shape)
    m += phone(t, n_up / fs, n_phone / fs, 150.0, rng)
    sc = StreamingCalibrator(synchronous=True)
    events = feed(sc, t, m)
    kinds = [e.kind for e in events]
    assert "drift" not in kinds and "forgot" not in kinds
    (dist,) = of_kind(events, "disturbance")
    assert dist.data["outcome"] in ("transient", "undecided")
    assert dist.t <= n_up / fs + sc.disturbance_rule.persist_s + 2.0
    assert any(e.kind == "accepted" and e.t >= dist.t for e in events)   # fitting went on
    assert sc.buffer.fraction > 0.9
    assert sc.calibration.model_error(truth()) < BOUND
