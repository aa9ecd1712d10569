"""The shared damped-LM loop reports converged / stalled / max_iter, and fit(full_output=True)
carries that status beside the calibration."""
import numpy as np
import pytest

from streamcal.fitting import FitResult, fit
from streamcal.fitting.damped_lm import (CONVERGED, DAMPING, MAX_ITER, STALLED, STATUSES,
                                         Damping, damped_lm, lag_grid, search_lag, trimmed_cost)
from streamcal.sim import simulate


def _curve_problem(wrong_sign: bool = False):
    """Least squares of y = exp(a t) + c over (a, c); ``wrong_sign`` hands the loop an uphill
    gradient (as a Jacobian with a sign error would), so no step can lower the cost."""
    t = np.linspace(0, 1, 40)
    y = np.exp(0.7 * t) + 0.3 + 0.01 * np.random.default_rng(0).standard_normal(len(t))

    def res(p):
        return np.exp(p[0] * t) + p[1] - y

    def linearize(p, r):
        J = np.stack([t * np.exp(p[0] * t), np.ones_like(t)], axis=1)
        g = J.T @ r
        return float(r @ r), J.T @ J, (-g if wrong_sign else g), None

    def evaluate(p, _ctx):
        r = res(p)
        return float(r @ r), r

    p0 = np.array([0.0, 0.0])
    r0 = res(p0)
    return p0, r0, float(r0 @ r0), linearize, evaluate


def test_converges_on_a_curve_fit():
    p0, r0, c0, linearize, evaluate = _curve_problem()
    out = damped_lm(p0, r0, c0, linearize=linearize, propose=lambda p, d: p + d,
                    evaluate=evaluate, max_iter=100, rtol=1e-10)
    assert out.status == CONVERGED and out.success
    assert np.allclose(out.x, [0.7, 0.3], atol=0.02)
    J = np.stack([np.linspace(0, 1, 40) * np.exp(out.x[0] * np.linspace(0, 1, 40)), np.ones(40)], 1)
    assert np.abs(J.T @ out.aux).max() < 1e-6    # the normal equations hold: a minimum


def test_stall_is_reported_as_stalled_not_converged():
    p0, r0, c0, linearize, evaluate = _curve_problem(wrong_sign=True)
    out = damped_lm(p0, r0, c0, linearize=linearize, propose=lambda p, d: p + d,
                    evaluate=evaluate, max_iter=100, rtol=1e-12)
    assert out.status == STALLED and not out.success
    assert out.iterations == 1
    assert np.array_equal(out.x, p0)          # nothing accepted
    assert "no step lowered the cost" in out.message


@pytest.mark.parametrize("damping", (DAMPING, Damping(start=1e-2, down=10.0, up=10.0, floor=1e-12)))
def test_the_damping_follows_its_schedule(damping):
    """λ read back from each trial step of a one-parameter problem (H = h: d = −g / (h + λ(h +
    10⁻¹²))): it starts at ``start``, is divided by ``down`` after an accepted step (not below
    ``floor``) and multiplied by ``up`` after a rejected one. Every third trial is rejected (an
    infinite cost), the others accepted."""
    h, lams, accepted = 2.0, [], []

    def linearize(x, _aux):
        return float(x[0] ** 2), np.array([[h]]), np.array([h * x[0]]), None

    def propose(x, d):
        lams.append((-h * x[0] / d[0] - h) / (h + 1e-12))
        return x + d

    def evaluate(cand, _ctx):
        ok = len(lams) % 3 != 2
        accepted.append(ok)
        return (0.0 if ok else np.inf), None

    damped_lm(np.array([1.0]), None, 1.0, linearize=linearize, propose=propose, evaluate=evaluate,
              max_iter=6, rtol=-1.0, damping=damping)     # rtol < 0: never converged
    expected = [damping.start]
    for ok in accepted[:-1]:
        expected.append(max(expected[-1] / damping.down, damping.floor) if ok
                        else expected[-1] * damping.up)
    np.testing.assert_allclose(lams, expected, rtol=1e-6)
    assert not all(accepted) and any(accepted)


def test_budget_exhausted_is_max_iter():
    p0, r0, c0, linearize, evaluate = _curve_problem()
    out = damped_lm(p0, r0, c0, linearize=linearize, propose=lambda p, d: p + d,
                    evaluate=evaluate, max_iter=2, rtol=1e-12)
    assert out.status == MAX_ITER and out.iterations == 2
    assert out.cost < c0


def test_lag_grid_and_search():
    grid = lag_grid(0.25)
    assert len(grid) == 51 and grid[0] == pytest.approx(-0.25) and grid[-1] == pytest.approx(0.25)
    lag, costs = search_lag(grid, lambda s: (s - 0.07) ** 2)
    assert lag == pytest.approx(0.07) and costs.shape == grid.shape
    rn = np.r_[np.ones(9), 100.0]               # one outlier capped at 3 × median
    assert trimmed_cost(rn) == pytest.approx(9 + 9)


@pytest.fixture(scope="module")
def track():
    return simulate(duration_s=30.0, seed=5).track


def test_fit_full_output_carries_the_status(track):
    plain = fit(track)
    full = fit(track, full_output=True)
    assert isinstance(full, FitResult)
    assert np.array_equal(full.calibration.K, plain.K) and np.array_equal(full.calibration.b, plain.b)
    assert full.status in STATUSES and full.iterations >= 1 and full.message


def test_fit_full_output_says_max_iter_when_the_budget_is_one(track):
    full = fit(track, kernel="cauchy", tau=1.0, max_iter=1, full_output=True)
    assert full.status == MAX_ITER and full.iterations == 1


def test_reference_method_reports_no_status(track):
    full = fit(track, method="l2_ellipsoid", full_output=True)
    assert full.status is None and "reports no solver status" in full.message


def test_registration_fit_full_output_carries_the_helper_status():
    tr = simulate(20.0, 3, effects={"time_lag": 0.02}).track
    full = fit(tr, add="time_lag", full_output=True)
    plain = fit(tr, add="time_lag")
    assert isinstance(full, FitResult) and full.status in STATUSES
    assert full.iterations >= 1 and full.message
    assert np.array_equal(full.calibration.K, plain.K)
    assert full.calibration.effects["time_lag"] == plain.effects["time_lag"]
