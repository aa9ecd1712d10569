"""The gravity- and gyro-tied residuals' own noise floor (streamcal.diagnosis.tied_noise): the
estimate agrees with the floor the simulator's known noise and reference error give; a model
judged on a tied residual is at the noise floor once nothing is missing (the loop closes, a
clean twin too) and is not while an effect it lacks keeps the residual above that floor."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.diagnosis import diagnose
from streamcal.diagnosis.noise import noise_floor
from streamcal.diagnosis.tied_noise import tied_floor
from streamcal.fitting.gravity import gravity_reference
from streamcal.fitting.gyro_lag import HORIZON_S
from streamcal.sim import simulate
from streamcal.sim.scenario import GYRO_NOISE
from tests._diagnose_helpers import fitter
from tests.test_gyro_lag import without_accel

BASE = ("hard_iron", "soft_iron")
#: The estimate is within this factor of the truth (its scatter: the horizontal motion of one
#: recording is not the vertical one it is measured from).
WITHIN = 1.5


def _mag_sigma(track) -> float:
    cov = track.covariates_at_mag()
    gyro = np.stack([cov[k] for k in ("gx", "gy", "gz")], axis=1)
    return noise_floor(track.mag, track.t_mag, gyro).floor


def _true_gravity_tied_floor(res) -> float:
    """The floor from the simulator's truth: the magnetometer noise the residual keeps (2 of
    3 components) and the true error of the gravity reference about the horizontal axis that
    turns the cone towards the field, scaled by the true field in the sensor."""
    truth = res.truth
    down, _ = gravity_reference(res.track).at(truth.t_sample)
    true_down = -truth.up_body
    x = truth.directions_body
    h = x - np.sum(x * true_down, axis=1, keepdims=True) * true_down
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    tilt = np.einsum("ni,ni->n", down - true_down, h)
    field2 = np.mean(np.sum((truth.directions @ truth.K.T) ** 2, axis=1))
    return float(np.sqrt(2 * truth.noise_uT ** 2 + field2 * np.mean(tilt ** 2)))


@pytest.mark.parametrize("seed", [11, 51, 52, 53, 60, 63])
def test_gravity_tied_floor_is_within_a_factor_of_the_truth(seed):
    res = simulate(60.0, seed)
    est = tied_floor("gravity_tied", res.track, res.truth.K, _mag_sigma(res.track), True)
    truth = _true_gravity_tied_floor(res)
    assert est.reliable and truth / WITHIN <= est.floor <= WITHIN * truth, (est, truth)
    # the reference's error is a part of its own, not the magnetometer's noise borrowed
    assert est.reference > 0.5 * est.magnetometer


@pytest.mark.parametrize("seed, noise", [(21, 0.2), (22, 0.4), (23, 0.7)])
def test_gyro_tied_floor_is_within_a_factor_of_the_truth(seed, noise):
    res = simulate(40.0, seed, noise_uT=noise)
    track = without_accel(res.track)
    est = tied_floor("gyro_tied", track, res.truth.K, _mag_sigma(res.track), True)
    radius = np.cbrt(abs(np.linalg.det(res.truth.K)))
    dt = 1.0 / 200.0     # the simulator's IMU rate
    truth = np.sqrt(4 * noise ** 2 + 2 * radius ** 2 * GYRO_NOISE ** 2 * HORIZON_S * dt)
    assert est.reliable and truth / WITHIN <= est.floor <= WITHIN * truth, (est, truth)


@pytest.mark.parametrize("gyro", [True, False], ids=["gyro", "accelerometer only"])
def test_the_gravity_reference_carries_its_own_tilt_error(gyro):
    """gravity_reference measures tilt_sigma's figure with the reference, exactly."""
    from streamcal.fitting.gravity import tilt_sigma

    track = simulate(30.0, 7).track
    if not gyro:
        track = type(track)({k: v for k, v in track.columns.items()
                             if k not in ("gx", "gy", "gz")}, track.metadata)
    ref = gravity_reference(track)
    assert (ref.tilt, ref.tilt_method) == tilt_sigma(track)
    assert ref.tilt > 0 and ("gyro-following" in ref.tilt_method) == gyro


def test_a_gravity_tied_diagnosis_integrates_the_gyro_once(monkeypatch):
    """The reference and its error share one integration of the gyro."""
    import streamcal.fitting.gravity as gravity

    calls = []
    frame = gravity._gyro_frame
    monkeypatch.setattr(gravity, "_gyro_frame", lambda *a: calls.append(1) or frame(*a))
    track = simulate(30.0, 33, effects={"time_lag": 0.02}).track
    d = diagnose(track, model=(*BASE, "time_lag"), fitter=fitter, candidates=[], ladder=False)
    assert d.residual == "gravity_tied" and d.tied_noise_floors["gravity_tied"]["reliable"]
    assert len(calls) == 1


def test_an_unmeasurable_magnetometer_floor_makes_the_tied_floor_unmeasurable():
    res = simulate(20.0, 5)
    est = tied_floor("gravity_tied", res.track, res.truth.K, float("nan"), False, "why not")
    assert not est.reliable and np.isnan(est.floor) and est.reason == "why not"
    assert est.to_dict()["floor"] is None


@pytest.mark.slow
@pytest.mark.parametrize("effect, size, seed", [("time_lag", 0.02, 31),
                                                ("mag_accel_misalignment", 0.06, 32)])
def test_the_loop_closes_on_the_tied_floor(effect, size, seed):
    """Hidden effect → named → added → at the tied residual's own floor; the clean twin (same
    motion and noise, no effect) with the same model too; the JSON says which floor judged."""
    track = simulate(60.0, seed, effects={effect: size}).track
    before = diagnose(track, fitter=fitter, ladder=False)
    assert before.verdict == "effect_missing" and before.candidates[0].effect == effect
    assert before.to_dict()["candidates"][0]["material"]
    model = (*BASE, effect)
    for recording in (track, simulate(60.0, seed).track):
        after = diagnose(recording, model=model, fitter=fitter, ladder=False)
        out = json.loads(json.dumps(after.to_dict()))
        floor = out["tied_noise_floors"]["gravity_tied"]
        assert after.residual == "gravity_tied" and floor["reliable"]
        assert after.verdict == "at_noise_floor", (after.rms, floor)
        assert after.rms <= 1.5 * floor["floor"]
        # the tied rms is above the magnetometer's floor: borrowing it would not close the loop
        assert after.rms > 1.5 * after.noise_floor
        assert "gravity-tied residual's own floor" in out["noise_floor_rule"]


@pytest.mark.slow
def test_a_tied_model_missing_an_effect_is_not_at_its_floor():
    """A lag in the model and a misalignment that is not, no candidates to name it: the
    gravity-tied residual stays well above its own floor, so the verdict is unexplained."""
    track = simulate(60.0, 33, effects={"time_lag": 0.02, "mag_accel_misalignment": 0.1}).track
    d = diagnose(track, model=(*BASE, "time_lag"), fitter=fitter, candidates=[], ladder=False)
    floor = d.floor_for("gravity_tied")
    assert d.residual == "gravity_tied" and np.isfinite(floor)
    assert d.rms > 1.5 * floor and d.verdict == "unexplained"


@pytest.mark.slow
def test_the_loop_closes_on_the_gyro_tied_floor():
    """Without an accelerometer a hidden lag is judged on the gyro-tied residual: once in the
    model, at that residual's own floor (two samples' magnetometer noise and the gyro's)."""
    track = without_accel(simulate(40.0, 52, effects={"time_lag": 0.03}).track)
    d = diagnose(track, model=(*BASE, "time_lag"), fitter=fitter, ladder=False)
    floor = d.tied_noise_floors["gyro_tied"]
    assert d.residual == "gyro_tied" and floor["reliable"]
    assert d.verdict == "at_noise_floor", (d.rms, floor)


@pytest.mark.slow
def test_clean_recordings_with_a_lag_in_the_model_are_never_unexplained():
    """No hidden effect, ``time_lag`` in the model (judged on the gravity-tied residual), noise
    0.2-0.7 µT, both output widths, hand rates 1-2.5 rad/s: the tied residual is at its own
    floor. (One seed may name a small frame misalignment: the simulated accelerometer's
    cross-axis gains tilt its frame against the magnetometer's.)"""
    verdicts = []
    for k, seed in enumerate(range(300, 312)):
        track = simulate(40.0, seed, noise_uT=(0.2, 0.4, 0.7)[k % 3], mag_bits=(16, 14)[k % 2],
                         rate_rad_s=(1.0, 1.5, 2.5)[k % 3]).track
        d = diagnose(track, model=(*BASE, "time_lag"), fitter=fitter, ladder=False)
        assert d.residual == "gravity_tied"
        verdicts.append(d.verdict)
    assert "unexplained" not in verdicts and verdicts.count("at_noise_floor") >= 11, verdicts
