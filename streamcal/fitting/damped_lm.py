"""The damped Gauss–Newton (Levenberg–Marquardt) loop of the gravity- and gyro-tied fits, its
status, and the lag grid both search before refining.

The loop (:func:`damped_lm`) is the problem-agnostic part: each round the problem linearizes
at the current state (cost, normal matrix H (P,P), gradient g (P,)); trial steps solve
(H + λ (diag H + 10⁻¹²)) d = −g, λ divided by 3 after an accepted step and multiplied by 4
after a rejected one (:data:`DAMPING`; the held fit of the diagnosis against a calibration
keeps its own ÷10 / ×10), at most :data:`TRIALS` trials per round. A trial is accepted when its
cost does not rise. The outcome is reported like scipy's ``OptimizeResult``:

    ``converged``  the accepted step lowered the cost by at most ``rtol`` × cost;
    ``stalled``    no trial step lowered the cost (or the cost is not finite);
    ``max_iter``   the round budget ran out while the cost was still falling.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

CONVERGED, STALLED, MAX_ITER = "converged", "stalled", "max_iter"
STATUSES = (CONVERGED, STALLED, MAX_ITER)
#: Trial steps per round.
TRIALS = 10


@dataclass(frozen=True)
class Damping:
    """The damping schedule: λ starts at ``start``, is divided by ``down`` (not below
    ``floor``) after an accepted step and multiplied by ``up`` after a rejected one."""

    start: float = 1e-3
    down: float = 3.0
    up: float = 4.0
    floor: float = 1e-9


#: The gravity- and gyro-tied fits' schedule.
DAMPING = Damping()


@dataclass
class LMStatus:
    """Outcome of :func:`damped_lm`: final ``x`` (state), its ``cost`` and auxiliary values
    ``aux``, ``status`` (one of :data:`STATUSES`), ``iterations`` (rounds started) and a
    human-readable ``message``."""

    x: Any
    cost: float
    aux: Any
    status: str
    iterations: int
    message: str

    @property
    def success(self) -> bool:
        return self.status == CONVERGED


def damped_step(H: np.ndarray, grad: np.ndarray, lam: float) -> np.ndarray:
    """Step d (P,) solving (H + λ (diag H + 10⁻¹²)) d = −grad."""
    return -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), grad)


def damped_lm(x0, aux0, cost0: float, *,
              linearize: Callable[[Any, Any], tuple],
              propose: Callable[[Any, np.ndarray], Any],
              evaluate: Callable[[Any, Any], tuple],
              max_iter: int, rtol: float, damping: Damping = DAMPING) -> LMStatus:
    """Minimize by damped Gauss–Newton from ``x0`` (with its ``aux0`` and cost ``cost0``).

    ``linearize(x, aux) -> (cost, H, grad, ctx)``: the merit at ``x`` for this round (it may
    re-weight: the trial costs are compared with this one) and its normal equations.
    ``propose(x, d) -> candidate`` applies the step d. ``evaluate(candidate, ctx) -> (cost,
    aux)``: the candidate's cost under this round's merit (``inf`` rejects it).
    """
    x, aux, cost = x0, aux0, float(cost0)
    lam = damping.start
    it = 0
    for it in range(1, max_iter + 1):
        cost, H, grad, ctx = linearize(x, aux)
        if not np.isfinite(cost):
            return LMStatus(x, cost, aux, STALLED, it, "the cost is not finite")
        accepted = None
        for _ in range(TRIALS):
            cand = propose(x, damped_step(H, grad, lam))
            cost1, aux1 = evaluate(cand, ctx)
            if cost1 <= cost:
                accepted = cand
                lam = max(lam / damping.down, damping.floor)
                break
            lam *= damping.up
        if accepted is None:
            return LMStatus(x, cost, aux, STALLED, it,
                            f"no step lowered the cost in {TRIALS} trials (λ = {lam:.3g})")
        drop = cost - cost1
        x, aux, cost = accepted, aux1, cost1
        if drop <= rtol * cost:
            return LMStatus(x, cost, aux, CONVERGED, it,
                            f"relative cost decrease {drop / cost if cost else 0.0:.3g} ≤ "
                            f"{rtol:g}")
    return LMStatus(x, cost, aux, MAX_ITER, it,
                    f"{max_iter} rounds used while the cost was still falling")


def lag_grid(half_width: float, step: float = 0.01) -> np.ndarray:
    """Lags (s) from −``half_width`` to +``half_width`` inclusive, ``step`` apart."""
    return np.arange(-half_width, half_width + step / 100, step)


def trimmed_cost(rn: np.ndarray, trust: np.ndarray | float = 1.0) -> float:
    """Σ trust · min(‖r‖, 3 median ‖r‖)² of the residual norms ``rn`` (N,): the cost the lag
    grids rank (robust to a minority of outliers, no kernel width needed)."""
    c = 3.0 * np.median(rn)
    return float(np.sum(trust * np.minimum(rn, c) ** 2))


def search_lag(grid: np.ndarray, cost_at: Callable[[float], float]) -> tuple[float, np.ndarray]:
    """(lag on ``grid`` (s) of least ``cost_at(lag)``, the costs (L,))."""
    costs = np.asarray([cost_at(float(lag)) for lag in grid])
    return float(grid[int(np.argmin(costs))]), costs
