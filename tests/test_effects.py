"""Effect terms: finite-difference checks of every derivative, physical/normalized round trips,
the model inversion used by ``Calibration.apply``, and input validation."""
import json

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.errors import MissingColumnsError, UnknownEffectError
from streamcal.model import (TERMS, build_effects, check_needs, invert_model, missing_columns,
                             validate_effect_params)

N = 40


def _cov(rng, n=N):
    return {"t": np.sort(rng.uniform(0, 300, n)), "temp": rng.normal(30, 5, n),
            "current": rng.uniform(0, 3, n), "pwm": rng.normal(50, 10, n),
            "ax": rng.normal(size=n)}


def _terms(rng):
    cov = _cov(rng)
    return cov, build_effects(list(TERMS), cov)


def _theta(term, rng):
    return rng.normal(0, 0.05, term.n_params())


@pytest.mark.parametrize("name", sorted(TERMS))
def test_jac_theta_matches_finite_differences(name):
    rng = np.random.default_rng(1)
    cov = _cov(rng)
    term = build_effects([name], cov)[0]
    theta, u = _theta(term, rng), rng.normal(size=(N, 3))
    jac = term.jac_theta(theta, u, cov)
    assert jac.shape == (N, 3, term.n_params())
    h = 1e-6
    for p in range(term.n_params()):
        d = np.zeros_like(theta)
        d[p] = h
        fd = (term.term(theta + d, u, cov) - term.term(theta - d, u, cov)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, p], fd, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("name", sorted(TERMS))
def test_jac_u_matches_finite_differences(name):
    rng = np.random.default_rng(2)
    cov = _cov(rng)
    term = build_effects([name], cov)[0]
    theta, u = _theta(term, rng), rng.normal(size=(N, 3))
    jac = term.jac_u(theta, u, cov)
    h = 1e-6
    fds = []
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        fds.append((term.term(theta, u + d, cov) - term.term(theta, u - d, cov)) / (2 * h))
    fd = np.stack(fds, axis=2)
    if jac is None:
        np.testing.assert_allclose(fd, 0.0, atol=1e-9)
    else:
        assert jac.shape == (N, 3, 3)
        np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)
    if name in ("temperature_scale", "axis_nonlinearity"):
        assert jac is not None and np.abs(fd).max() > 1e-3


@pytest.mark.parametrize("name", sorted(TERMS))
def test_physical_round_trip(name):
    rng = np.random.default_rng(3)
    cov = _cov(rng)
    term = build_effects([name], cov)[0]
    theta = _theta(term, rng)
    params = json.loads(json.dumps(term.to_physical(theta, 37.5)))
    np.testing.assert_allclose(term.from_physical(params, 37.5), theta, rtol=1e-12)


def _sensor(rng):
    K = np.triu(rng.normal(0, 2, (3, 3)), 1) + np.diag(rng.uniform(40, 60, 3))
    return K, rng.normal(0, 20, 3)


@pytest.mark.parametrize("names", [[n] for n in sorted(TERMS)] + [sorted(TERMS)])
def test_apply_of_physical_parameters_reproduces_normalized_model(names):
    """A fit on normalized data (m_n = (m − c)/s) converted with to_physical and applied to the
    physical readings gives back the directions the normalized model used."""
    rng = np.random.default_rng(4)
    n = 200
    cov = _cov(rng, n)
    terms = build_effects(names, cov)
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    K_n, b_n = _sensor(rng)
    K_n, b_n = K_n / 50, b_n / 50
    thetas = [_theta(t, rng) for t in terms]
    u_n = x @ K_n.T
    m_n = u_n + b_n + sum(t.term(th, u_n, cov) for t, th in zip(terms, thetas))
    center, scale = np.array([10.0, -5.0, 30.0]), 47.0
    m = center + scale * m_n
    cal = Calibration(K=K_n * scale, b=center + scale * b_n, model=("hard_iron", "soft_iron", *names),
                      effects={t.name: t.to_physical(th, scale) for t, th in zip(terms, thetas)}, n=n)
    cal = Calibration.from_json(cal.to_json())  # the file round trip validates the parameters
    np.testing.assert_allclose(cal.apply(m, cov), x, atol=1e-9)


def test_invert_model_handles_strong_nonlinear_terms():
    rng = np.random.default_rng(5)
    cov = _cov(rng, 500)
    K, b = _sensor(rng)
    x = rng.normal(size=(500, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    effects = {"axis_nonlinearity": {"R": 50.0, "a": [0.08, -0.05, 0.1]},
               "temperature_scale": {"T0": 30.0, "s": [0.004, -0.003, 0.002]}}
    cal = Calibration(K=K, b=b, effects=effects, n=500)
    u = x @ K.T
    terms = [TERMS[k].from_params(v) for k, v in effects.items()]
    m = u + b + sum(t.term(t.from_physical(effects[t.name], 1.0), u, cov) for t in terms)
    np.testing.assert_allclose(invert_model(cal, m, cov), x, atol=1e-10)
    # without the effects the directions are visibly wrong: the inversion is doing the work
    assert np.abs(Calibration(K=K, b=b, n=500).apply(m) - x).max() > 1e-2


def test_apply_without_needed_covariate_names_the_column():
    cal = Calibration(K=np.eye(3), b=np.zeros(3), n=1,
                      effects={"temperature_offset": {"T0": 20.0, "c": [1.0, 0.0, 0.0]}})
    with pytest.raises(MissingColumnsError, match="temp"):
        cal.apply(np.ones((4, 3)), {"t": np.arange(4.0)})


@pytest.mark.parametrize("effects, words", [
    ({"temperature_offset": {"T0": 25.0, "c": [1, 2]}}, ["temperature_offset", "'c'"]),
    ({"temperature_offset": {"c": [1, 2, 3]}}, ["temperature_offset", "'T0'"]),
    ({"temperature_scale": {"T0": 25.0, "s": [1, 2, 3], "k": 1}}, ["temperature_scale", "'k'"]),
    ({"time_drift": {"t0": "now", "d": [0, 0, 0]}}, ["time_drift", "'t0'"]),
    ({"axis_nonlinearity": {"R": -1.0, "a": [0, 0, 0]}}, ["axis_nonlinearity", "'R'"]),
    ({"aux_interference": {"channels": {"i": {"a0": 0.0, "g": [0, None, 0]}}}},
     ["aux_interference.channels.i", "'g'"]),
    ({"aux_interference": {"channels": {}}}, ["aux_interference", "'channels'"]),
    ({"time_lag": {"tau": float("nan")}}, ["time_lag", "'tau'"]),
    ({"mag_accel_misalignment": {"rotation": [0, 0], "dip": 1.0}}, ["mag_accel_misalignment", "'rotation'"]),
])
def test_validate_effect_params_names_effect_and_parameter(effects, words):
    with pytest.raises(ValueError) as info:
        validate_effect_params(effects)
    for word in words:
        assert word in str(info.value)


def test_valid_params_pass_validation():
    validate_effect_params({"temperature_offset": {"T0": 25.0, "c": [0.1, 0.2, 0.3]},
                            "time_lag": {"tau": 0.01},
                            "mag_accel_misalignment": {"rotation": [0.01, 0, 0], "dip": 1.1},
                            "aux_interference": {"channels": {"i": {"a0": 1.0, "g": [1, 2, 3]}}}})


def test_build_effects_rejects_unknown_and_missing():
    with pytest.raises(UnknownEffectError, match="temprature_offset"):
        build_effects(["temprature_offset"], {"t": np.zeros(3)})
    with pytest.raises(MissingColumnsError, match="temp"):
        build_effects(["temperature_offset"], {"t": np.zeros(3)})
    with pytest.raises(MissingColumnsError, match="auxiliary"):
        build_effects(["aux_interference"], {"t": np.zeros(3), "temp": np.zeros(3)})
    assert build_effects(["hard_iron", "soft_iron", "time_lag"], {}) == []


class _FakeTrack:
    def __init__(self, cols, aux=()):
        self.cols, self.aux_names = set(cols), list(aux)

    def has(self, name):
        return name in self.cols


def test_check_needs_names_missing_columns():
    track = _FakeTrack({"t", "mx", "my", "mz", "ax", "ay"})
    missing = missing_columns(["temperature_offset", "aux_interference", "mag_accel_misalignment",
                               "time_lag", "time_drift", "soft_iron"], track)
    assert missing["temperature_offset"] == ["temp"]
    assert missing["mag_accel_misalignment"] == ["az"]
    assert "aux_interference" in missing and "time_lag" in missing
    assert "time_drift" not in missing and "soft_iron" not in missing
    with pytest.raises(MissingColumnsError, match="az"):
        check_needs(["mag_accel_misalignment"], track)
    check_needs(["time_lag"], _FakeTrack({"gx", "gy", "gz"}))
    with pytest.raises(UnknownEffectError):
        check_needs(["warp_drive"], track)
