"""StreamingCalibrator: first fit on coverage, drift → forget and refit, guard, slow fitter."""
import threading

import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.calibration import Calibration
from streamcal.errors import InsufficientDataError
from streamcal.fitting.sphere_stream import fit_sphere_stream
from streamcal.stream import CalibrationStore, CoverageBuffer, StreamingCalibrator

B_TRUE = np.array([10.0, -20.0, 30.0])
RADIUS = 48.0


def sphere_fitter(snap):
    """A simple injected fitter: the one-pass sphere fit, with its rms."""
    K, b = fit_sphere_stream(snap.m)
    r = np.linalg.norm(snap.m - b, axis=1) - K[0, 0]
    return Calibration(K=K, b=b, rms=float(np.sqrt(np.mean(r ** 2))), n=len(snap.m),
                       method="sphere_stream")


def spiral_track(duration, jump_at=None, jump=(30.0, 0.0, 0.0), rate=100.0, period=60.0, seed=0):
    """Samples of a board turning through every direction every ``period`` s (µT)."""
    t = np.arange(0.0, duration, 1.0 / rate)
    th = np.pi * ((t / period) % 1.0)
    ph = 2 * np.pi * t / 4.0
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    b = np.tile(B_TRUE, (len(t), 1))
    if jump_at is not None:
        b[t >= jump_at] += jump
    rng = np.random.default_rng(seed)
    return t, RADIUS * d + b + rng.normal(scale=0.3, size=d.shape)


def feed(sc, t, m, block=50):
    events = []
    for i in range(0, len(t), block):
        events += sc.ingest(SampleBlock(t=t[i:i + block], mag=m[i:i + block]))
    return events


def kinds(events):
    return [e.kind for e in events]


def test_first_fit_when_coverage_suffices():
    t, m = spiral_track(60.0)
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True)
    events = feed(sc, t, m)
    started = [e for e in events if e.kind == "fit_started"]
    assert started and started[0].data["coverage"] >= 0.35
    assert "accepted" in kinds(events)
    np.testing.assert_allclose(sc.calibration.b, B_TRUE, atol=0.3)
    out = sc.apply(SampleBlock(t=t[:100], mag=m[:100]))
    assert np.abs(np.linalg.norm(out, axis=1) - RADIUS).max() < 2.0
    coverage = [e for e in events if e.kind == "coverage"]
    assert [e.data["coverage"] for e in coverage] == sorted(e.data["coverage"] for e in coverage)


def test_drift_triggers_forgetting_and_refit():
    t, m = spiral_track(180.0, jump_at=100.0)
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True)
    events = feed(sc, t, m)
    k = kinds(events)
    assert k.count("drift") == 1
    drift = events[k.index("drift")]
    # The disagreement must last DisturbanceRule.min_age_s (3 s: a passing phone has turned
    # around by then) and is judged once per stage (256 rows, 2.56 s here).
    assert 100.0 + 3.0 <= drift.t <= 100.0 + 3.0 + 2.6 and drift.data["value"] > drift.data["limit"]
    assert drift.data["reason"] == "new_shell" and "disturbance" not in k
    forgot = events[k.index("forgot")]
    assert k.index("forgot") == k.index("drift") + 1
    assert forgot.data["dropped"] > 0 and forgot.data["onset"] >= 99.99
    assert "accepted" in k[k.index("forgot"):]
    np.testing.assert_allclose(sc.calibration.b, B_TRUE + [30.0, 0.0, 0.0], atol=0.5)
    assert sc.buffer.snapshot().t.min() >= forgot.data["onset"]
    assert not sc.stale


def test_no_drift_without_change():
    t, m = spiral_track(150.0)
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True)
    assert "drift" not in kinds(feed(sc, t, m))


def test_worse_candidate_is_rejected_and_calibration_kept():
    t, m = spiral_track(120.0)
    calls = []

    def fitter(snap):
        cal = sphere_fitter(snap)
        calls.append(cal)
        return cal if len(calls) == 1 else cal.replace(b=cal.b + [4.0, 0.0, 0.0])

    sc = StreamingCalibrator(fitter=fitter, synchronous=True)
    events = feed(sc, t, m)
    rejected = [e for e in events if e.kind == "rejected"]
    assert len(calls) >= 2 and len(rejected) == len(calls) - 1
    assert all(e.data["reason"] == "worse_on_holdout" and e.data["value"] > e.data["limit"]
               for e in rejected)
    np.testing.assert_allclose(sc.calibration.b, calls[0].b)


def test_failed_fit_is_reported_and_ingest_continues():
    t, m = spiral_track(40.0)

    def failing(snap):
        raise InsufficientDataError("not enough directions")

    sc = StreamingCalibrator(fitter=failing, synchronous=True)
    events = feed(sc, t, m)
    assert "fit_failed" in kinds(events) and sc.calibration is None
    assert "not enough directions" in [e for e in events if e.kind == "fit_failed"][0].message


def test_ingest_keeps_flowing_while_a_slow_fit_runs():
    t, m = spiral_track(120.0)
    started, release = threading.Event(), threading.Event()
    n_calls = []

    def slow(snap):
        n_calls.append(len(snap))
        started.set()
        assert release.wait(30), "test never released the fitter"
        return sphere_fitter(snap)

    sc = StreamingCalibrator(fitter=slow)
    i, events = 0, []
    while not started.is_set() and i < len(t):          # until the first fit has begun
        events += sc.ingest(SampleBlock(t=t[i:i + 50], mag=m[i:i + 50]))
        i += 50
    assert started.wait(10) and sc.fit_in_flight
    ingested_before, stored_before = sc.n_ingested, sc.buffer.n_samples
    for j in range(i, len(t), 50):                      # the fitter is blocked meanwhile
        events += sc.ingest(SampleBlock(t=t[j:j + 50], mag=m[j:j + 50]))
    assert sc.n_ingested == ingested_before + (len(t) - i)      # nothing dropped
    assert sc.buffer.n_samples > stored_before
    assert kinds(events).count("fit_started") == 1 and len(n_calls) == 1   # one in flight
    assert sc.calibration is None
    release.set()
    events = sc.drain(timeout=30)
    assert "accepted" in kinds(events) and not sc.fit_in_flight


def test_single_sample_blocks_are_staged():
    t, m = spiral_track(2.0)
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True, stage=64)
    for k in range(63):
        sc.ingest(SampleBlock(t=t[k:k + 1], mag=m[k:k + 1]))
    assert sc.buffer.n_samples == 0 and sc.sphere.n == 0
    sc.ingest(SampleBlock(t=t[63:64], mag=m[63:64]))
    assert sc.sphere.n == 64
    sc.ingest(SampleBlock(t=t[64:65], mag=m[64:65]))
    sc.poll()
    assert sc.sphere.n == 65


def test_memory_constant_after_many_samples():
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True)
    t, m = spiral_track(100.0)
    feed(sc, t, m)
    arrays = lambda: sc.nbytes
    before = arrays()
    t2, m2 = spiral_track(600.0, seed=1)
    feed(sc, t2 + 100.0, m2, block=500)
    assert arrays() == before and sc.buffer.n_samples <= sc.buffer.capacity
    assert len(sc.recaller.remembered) <= sc.recaller.capacity


def test_nan_rows_and_covariates():
    t, m = spiral_track(60.0)
    m[::7] = np.nan
    temp = 20.0 + t / 10.0
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True,
                             buffer=CoverageBuffer(covariates=("temp",)))
    for i in range(0, len(t), 50):
        sc.ingest(SampleBlock(t=t[i:i + 50], mag=m[i:i + 50], temp=temp[i:i + 50]))
    assert sc.n_ingested == np.isfinite(m).all(axis=1).sum()
    snap = sc.buffer.snapshot()
    np.testing.assert_allclose(snap.covariates["temp"], 20.0 + snap.t / 10.0)


def test_accepted_calibration_is_stored_and_reloaded(tmp_path):
    t, m = spiral_track(60.0)
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True,
                             store=CalibrationStore(tmp_path / "state"))
    events = feed(sc, t, m)
    assert "stored" in kinds(events)
    again = StreamingCalibrator(fitter=sphere_fitter, store=CalibrationStore(tmp_path / "state"))
    loaded = again.poll()
    assert kinds(loaded) == ["loaded"]
    np.testing.assert_allclose(again.calibration.K, sc.calibration.K)


def test_with_the_real_batch_fit():
    K = np.array([[50.0, 2.0, -1.0], [0.0, 46.0, 1.5], [0.0, 0.0, 53.0]])
    t, m = spiral_track(70.0)
    m = (m - B_TRUE) / RADIUS @ K.T + B_TRUE          # soft iron
    sc = StreamingCalibrator(synchronous=True)        # default fitter: streamcal.fitting.fit
    events = feed(sc, t, m)
    assert "accepted" in kinds(events), [e.message for e in events if e.kind != "coverage"]
    cal = sc.calibration
    assert cal.model_error(Calibration(K=K, b=B_TRUE, n=1)) < 0.02


def test_covariates_sampled_at_other_rows_are_held():
    t = np.arange(10.0)
    mag = np.full((10, 3), np.nan)
    mag[1::2] = [[60.0, 0.0, 0.0]]
    temp = np.where(np.arange(10) % 2 == 0, 20.0 + t, np.nan)     # temp only on the other rows
    sc = StreamingCalibrator(fitter=sphere_fitter, synchronous=True, stage=1,
                             buffer=CoverageBuffer(covariates=("temp",)))
    sc.ingest(SampleBlock(t=t[:5], mag=mag[:5], temp=temp[:5]))
    sc.ingest(SampleBlock(t=t[5:], mag=mag[5:], temp=temp[5:]))
    # the stored sample of that direction is the newest: t=9 with temp held from t=8
    snap = sc.buffer.snapshot()
    np.testing.assert_allclose(snap.covariates["temp"], snap.t + 19.0)
