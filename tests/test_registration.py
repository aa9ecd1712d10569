"""Gravity-tied registration fit: Jacobians against finite differences, recovery of a simulated
misalignment and time lag, effect parameters that a calibration file accepts."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.calibration import Calibration
from streamcal.errors import InputError, MissingColumnsError
from streamcal.fitting import fit
from streamcal.model import validate_effect_params
from streamcal.fitting.registration import (LAG_STEP, _Problem, fit_with_registration, gravity_reference,
                                          registration_fit)
from streamcal.sim import simulate
from streamcal.inputs.track import Track

BASE = ("hard_iron", "soft_iron")


@pytest.fixture(scope="module")
def lagged():
    return simulate(40.0, 3, effects={"time_lag": 0.03, "mag_accel_misalignment": 0.04})


def test_gravity_reference_is_close_to_the_true_down(lagged):
    tr, truth = lagged.track, lagged.truth
    down, trust = gravity_reference(tr).at(truth.t_sample)
    err = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", down, -truth.up_body), -1, 1)))
    raw = -np.stack([tr.covariates_at_mag()[k] for k in ("ax", "ay", "az")], 1)
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    err_raw = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", raw, -truth.up_body), -1, 1)))
    assert np.sqrt(np.mean(err ** 2)) < 0.6 * np.sqrt(np.mean(err_raw ** 2))
    assert np.all((trust > 0) & (trust <= 1))


def test_jacobian_matches_finite_differences(lagged):
    tr = lagged.track
    cov = {k: np.asarray(v)[:300] for k, v in tr.covariates_at_mag().items()}
    from streamcal.model import build_effects

    terms = build_effects(["temperature_scale"], cov)
    prob = _Problem(np.asarray(tr.mag[:300]), cov, gravity_reference(tr), terms, True, True)
    rng = np.random.default_rng(0)
    K = np.triu(rng.normal(0, 2, (3, 3))) + np.diag([48, 50, 47.0])
    b, th = rng.normal(0, 20, 3), [np.array([1e-3, -2e-3, 5e-4])]
    R0 = Rotation.from_rotvec([0.02, -0.01, 0.03]).as_matrix()
    dip, lag = 0.5, 0.012
    h = rng.normal(size=(300, 3))
    p0 = prob.pack(K, b, th, dip, lag)
    J = prob.jacobian(*prob.unpack(p0, R0, lag), h)
    for k in range(len(p0)):
        # τ: ĝ is piecewise linear between IMU rows, so use the solver's own central step
        step = 1e-6 * max(1.0, abs(p0[k])) if k != len(p0) - 1 else LAG_STEP
        pp, pm = p0.copy(), p0.copy()
        pp[k] += step
        pm[k] -= step
        num = (prob.residual(*prob.unpack(pp, R0, lag), h)
               - prob.residual(*prob.unpack(pm, R0, lag), h)) / (2 * step)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-3, atol=1e-4 * np.abs(num).max() + 1e-9,
                                   err_msg=f"parameter {k}")


def test_headings_minimise_the_residual_along_the_circle(lagged):
    tr = lagged.track
    cov = tr.covariates_at_mag()
    prob = _Problem(np.asarray(tr.mag), cov, gravity_reference(tr), [], False, False)
    cal = fit(tr)
    h = prob.headings(cal.K, cal.b, [], np.eye(3), 0.52, 0.0)
    r = np.linalg.norm(prob.residual(cal.K, cal.b, [], np.eye(3), 0.52, 0.0, h), axis=1)
    g, _ = prob.down(0.0)
    side = np.cross(g, h)
    for angle in (-0.02, 0.02):  # turning any heading either way makes it worse
        h2 = np.cos(angle) * h + np.sin(angle) * side
        r2 = np.linalg.norm(prob.residual(cal.K, cal.b, [], np.eye(3), 0.52, 0.0, h2), axis=1)
        assert np.mean(r2 >= r - 1e-9) > 0.99


def test_recovers_lag_and_rotation(lagged):
    res = registration_fit(lagged.track, (*BASE, "mag_accel_misalignment", "time_lag"))
    truth = lagged.truth.effects
    assert res.lag == pytest.approx(truth["time_lag"]["tau"], abs=0.003)
    R_true = Rotation.from_rotvec(truth["mag_accel_misalignment"]["rotation"])
    err = (Rotation.from_matrix(res.rotation) * R_true.inv()).magnitude()
    assert err < 0.4 * R_true.magnitude()
    assert res.dip == pytest.approx(truth["mag_accel_misalignment"]["dip"], abs=0.02)
    base = registration_fit(lagged.track, BASE)
    assert res.rms < 0.8 * base.rms


def test_calibration_effects_are_valid_and_round_trip(lagged):
    cal = fit_with_registration(lagged.track, (*BASE, "mag_accel_misalignment", "time_lag"))
    validate_effect_params(cal.effects)
    assert set(cal.effects) == {"mag_accel_misalignment", "time_lag"}
    back = Calibration.from_json(cal.to_json())
    assert back.effects == cal.effects and back.model == cal.model
    x = cal.apply(lagged.track.mag)  # registration effects leave apply unchanged
    np.testing.assert_allclose(x, np.linalg.solve(cal.K, (lagged.track.mag - cal.b).T).T)


def test_needs_an_accelerometer_track():
    res = simulate(10.0, 1)
    tr = res.track
    mag_only = Track.from_arrays(t=tr.t_mag, mag=tr.mag)
    with pytest.raises(MissingColumnsError, match="ax"):
        fit_with_registration(mag_only, (*BASE, "mag_accel_misalignment"))
    with pytest.raises(InputError):
        fit_with_registration(tr.mag, (*BASE, "time_lag"))
    with pytest.raises(InputError):
        fit_with_registration(tr, (*BASE, "time_lag"), sensor="accel")
