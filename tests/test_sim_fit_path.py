"""The default fit's path on a hand tumble: what tests/test_outlier_free_start.py and
tests/test_polish_start.py check on FreeIMU-cal's real 1000 samples (one Cauchy LM step on an
outlier-free start, then a Geman–McClure polish that converges in two iterations)."""
from __future__ import annotations

from streamcal.fitting import fit
from streamcal.sim import simulate

from ._shared_checks import refine_iterations


def test_a_hand_tumble_takes_one_cauchy_step_and_a_two_iteration_polish(monkeypatch):
    """1000 samples of a simulated hand tumble take the real log's path: three LM iterations in
    all, the polish converged in at most two."""
    iterations = refine_iterations(monkeypatch)
    for seed in (0, 1, 2):
        del iterations[:]
        m = simulate(60.0, seed, motor=False).track.mag[:1000]
        result = fit(m, full_output=True, check_coverage=False)
        assert sum(iterations) == 3 and result.status == "converged" and result.iterations <= 2
