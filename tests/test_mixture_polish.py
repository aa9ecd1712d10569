"""The mixture polish (streamcal.fitting.mixture_polish): its kernel, its EM, when autocal runs
it, and that it does not make the paper-protocol fit worse under heavy contamination."""
import numpy as np
import pytest

import streamcal.fitting.autocal as autocal_module
from streamcal.fitting import fit
from streamcal.fitting.mixture_polish import GaussUniform, heavy_tail, mixture_fit
from streamcal.sim import paper_protocol


def _error(cal, K, b):
    A, R = np.column_stack([cal.K, cal.b]), np.column_stack([K, b])
    return np.linalg.norm(A - R) / np.linalg.norm(R)


def test_kernel_derivatives_match_finite_differences():
    k = GaussUniform(sigma=0.7, kappa=0.05)
    s = np.linspace(0.01, 12.0, 61)
    rho, d1, d2 = k.evaluate(s)
    h = 1e-6
    np.testing.assert_allclose(rho, k.rho(s))
    np.testing.assert_allclose(d1, (k.rho(s + h) - k.rho(s - h)) / (2 * h), rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(d2, (k.evaluate(s + h)[1] - k.evaluate(s - h)[1]) / (2 * h),
                               rtol=1e-4, atol=1e-8)
    rho, d1, d2 = k.evaluate(np.array([0.0, 25 * 0.49]))
    assert rho[0] == 0 and d1[0] == pytest.approx(1.0)
    assert d1[-1] < 1e-3            # redescending: a sample 5σ off barely counts


def test_em_recovers_the_inlier_width_under_a_flat_outlier_density():
    rng = np.random.default_rng(1)
    r = np.concatenate([np.abs(rng.normal(0, 1.0, 7000)), rng.uniform(0, 60, 3000)])
    sigma, kappa, n_in = mixture_fit(r, 1.2)      # start inflated, as a truncated median is
    assert sigma == pytest.approx(1.0, rel=0.03)
    assert n_in == pytest.approx(7000, rel=0.03)
    # κ = f₀σ√(2π)/n_in with f₀ = 3000/60/2 outliers per unit of signed residual
    assert kappa == pytest.approx(25 * np.sqrt(2 * np.pi) / 7000, rel=0.2)
    assert heavy_tail(r, 1.0)
    assert not heavy_tail(np.abs(rng.normal(0, 1.0, 10000)), 1.0)


def _gauss_uniform_fits(monkeypatch):
    """Record the kernels of every refine run autocal makes."""
    calls = []
    real = autocal_module.refine

    def spy(*args, **kwargs):
        calls.append(type(kwargs.get("kernel")).__name__)
        return real(*args, **kwargs)

    monkeypatch.setattr(autocal_module, "refine", spy)
    return calls


@pytest.mark.parametrize("eta", [0.0, 0.01])
def test_not_run_on_clean_or_lightly_contaminated_data(monkeypatch, eta):
    calls = _gauss_uniform_fits(monkeypatch)
    for seed in range(3):
        m, *_ = paper_protocol(1000, 1.0, eta, seed)
        fit(m, check_coverage=False)
    assert calls and "GaussUniform" not in calls


def test_runs_under_heavy_contamination(monkeypatch):
    calls = _gauss_uniform_fits(monkeypatch)
    m, *_ = paper_protocol(1000, 1.0, 0.30, 0)
    fit(m, check_coverage=False)
    assert "GaussUniform" in calls


@pytest.mark.parametrize("eta", [0.10, 0.30])
def test_not_worse_than_the_gm_polish_under_contamination(monkeypatch, eta):
    """σ = 1, outliers within ±100: mean error over 12 seeds within 5 % of the oracle's, and at
    10 % outliers (where the gain is larger than the seed spread of 12 data sets) not above the
    fit without the step. (bench_contamination.py, seeds 0–199, 30 %: 1.030× the oracle against
    1.052× without; 10 %: 1.008× against 1.038×. On 24 seeds at 30 % the two are even.)"""
    with_step, without, oracle = [], [], []
    for seed in range(12):
        m, K, b, inl = paper_protocol(1000, 1.0, eta, seed)
        with_step.append(_error(fit(m, check_coverage=False), K, b))
        oracle.append(_error(fit(m[inl], kernel="l2", check_coverage=False), K, b))
        with monkeypatch.context() as mp:
            mp.setattr(autocal_module, "mixture_polish", lambda result, sigma, refine_with: (result, sigma))
            without.append(_error(fit(m, check_coverage=False), K, b))
    assert np.mean(with_step) <= 1.05 * np.mean(oracle)
    if eta == 0.10:
        assert np.mean(with_step) <= np.mean(without)
