"""On data whose clean algebraic start shows no outlier at all, the default fit's Cauchy pass is
a single LM step (``autocal.OUTLIER_FREE_STEPS``) before the Geman–McClure polish; with any
outlier beyond the fit's own rule the full pass runs as before."""
import numpy as np
import pytest

from streamcal.fitting import autocal, fit
from streamcal.sim import paper_protocol

from ._shared_checks import refine_iterations


def _distance(cal, ref) -> float:
    """Paper eq. 40: ‖[K b] − [K_ref b_ref]‖_F / ‖[K_ref b_ref]‖_F."""
    a, r = np.column_stack([cal.K, cal.b]), np.column_stack([ref.K, ref.b])
    return float(np.linalg.norm(a - r) / np.linalg.norm(r))


def _cauchy_passes(monkeypatch):
    """Spy on autocal's LM runs: the max_iter of each Cauchy run, in order."""
    calls = []
    original = autocal.refine

    def spy(*args, **kwargs):
        if kwargs["kernel"].name == "cauchy":
            calls.append(kwargs["max_iter"])
        return original(*args, **kwargs)

    monkeypatch.setattr(autocal, "refine", spy)
    return calls


def _full_pass(monkeypatch):
    """The fit as before the single step: the full loose Cauchy pass on every clean start."""
    monkeypatch.setattr(autocal, "OUTLIER_FREE_STEPS", 300)
    monkeypatch.setattr(autocal, "OUTLIER_FREE_LAM0", autocal.CLEAN_LAM0)


@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_one_step_on_outlier_free_data_lands_where_the_full_pass_does(monkeypatch, sigma):
    data = [paper_protocol(1000, sigma, 0.0, seed)[0] for seed in range(4)]
    calls = _cauchy_passes(monkeypatch)
    fast = [fit(m, check_coverage=False) for m in data]
    # each fit starts with one Cauchy step (another width round may follow when σ̂ moved > 5 %)
    assert calls.count(1) == len(data) and set(calls) <= {1, 300}
    del calls[:]
    _full_pass(monkeypatch)
    full = [fit(m, check_coverage=False) for m in data]
    assert 1 not in calls
    # the polish converges to its rtol in both; its width σ̂ is read after one step instead of
    # the full pass, which moves its optimum by ≤ 1.3e-5 on these seeds (σ = 2) — under 1 % of
    # the calibration's own error against the truth (~3e-3 at σ = 2, ~1e-3 at σ = 0.5)
    errors = [_distance(a, b) for a, b in zip(fast, full)]
    assert max(errors) < (2e-5 if sigma > 1 else 5e-6), errors


def test_a_few_gross_outliers_keep_the_full_pass(monkeypatch):
    m = paper_protocol(1000, 1.0, 0.01, 0)[0]
    calls = _cauchy_passes(monkeypatch)
    cal = fit(m, check_coverage=False)
    assert calls and 1 not in calls
    _full_pass(monkeypatch)
    assert _distance(cal, fit(m, check_coverage=False)) == 0.0


def test_freeimucal_takes_three_lm_iterations(real_data_dir, monkeypatch):
    m = np.loadtxt(real_data_dir / "freeimucal_mag_data.txt", max_rows=1000, usecols=(0, 1, 2))
    iterations = refine_iterations(monkeypatch)
    fit(m)
    assert sum(iterations) == 3            # 1 Cauchy step + 2 polish iterations (was 4)


def test_the_gate_also_holds_for_a_start_fitted_on_the_spread_subset(monkeypatch):
    """Above CLEAN_START_ROWS the start is fitted on the stage-1 subset; the gate reads the
    residuals of every sample at it, as for a short recording."""
    monkeypatch.setattr(autocal, "CLEAN_START_ROWS", 500)
    calls = _cauchy_passes(monkeypatch)
    fit(paper_protocol(2000, 1.0, 0.0, 4)[0], check_coverage=False)
    assert calls[0] == 1
    del calls[:]
    fit(paper_protocol(2000, 1.0, 0.01, 4)[0], check_coverage=False)
    assert calls and 1 not in calls
