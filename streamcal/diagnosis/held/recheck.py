"""Re-check, at the re-estimated point, that each re-estimated parameter is determined (issue #10).

:func:`streamcal.diagnosis.held.choose_free` picks the estimated set from the Cramér–Rao error
at the *given* calibration. On a slice that leaves a combination of K nearly free, the robust
fit can drift along it to a point where that prediction no longer holds (a real 20-minute
flight: K_xy 404 ± 825 µT at a field radius of 23 µT, the fit at its iteration cap). So after
every fit :func:`settle` checks each estimated parameter p at the fitted point:

* its error σ_p = max(the fit's own σ̂²(AᵀWA)⁻¹ error, the Cramér–Rao error recomputed at the
  fitted K and b with the noise max(noise floor, σ̂ of the fit's inliers));
* its value against a plausible range, r the field radius of the given calibration:
  off-diagonal |K_ij| ≤ r, diagonal K_ii and the radius within [r/2, 2r],
  |b_i − b_i,given| ≤ r
  (:func:`plausible_range`).

A parameter with σ_p above the tolerance, or outside its range by more than
:data:`SUSPICIOUS_SIGMAS` σ_p, fails. The worst failure (the largest σ_p / tolerance; an
implausible value before a merely uncertain one) is held at its given value and the fit is
repeated from the given calibration, until no estimated parameter fails. Parameters the caller
must keep (b without a calibration) are never held: when one fails it stays estimated and is
reported as suspicious.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ...fitting.entries import B_INDEX, K_INDEX, RADIUS
from .fit import HeldFit, jacobian, predicted_errors, project

#: A value further than this many of its own σ outside its plausible range is implausible.
SUSPICIOUS_SIGMAS = 3.0
#: Plausible diagonal K_ii, as a fraction of the field radius r of the given calibration.
DIAG_RANGE = (0.5, 2.0)


def plausible_range(name: str, r: float, b_given: np.ndarray) -> tuple[float, float]:
    """(low, high) of a physically plausible value of core parameter ``name`` (sensor unit),
    ``r`` the field radius of the given calibration and ``b_given`` (3,) its offset."""
    if name in B_INDEX:
        c = float(b_given[B_INDEX[name]])
        return c - r, c + r
    i, j = (0, 0) if name == RADIUS else K_INDEX[name]
    if i == j:
        return DIAG_RANGE[0] * r, DIAG_RANGE[1] * r
    return -r, r


@dataclass
class Settled:
    """Outcome of :func:`settle`: the last ``fit`` (every estimated parameter passed, bar kept
    ones), the estimated set ``free``, ``rounds`` (fits made), ``held_after_fit`` (one entry per
    parameter held by the re-check: name, value and σ it had, the reason) and ``suspicious``
    ({name: entry} of kept parameters that failed)."""

    fit: HeldFit
    free: list
    rounds: int
    held_after_fit: list = field(default_factory=list)
    suspicious: dict = field(default_factory=dict)


def check(fit: HeldFit, free: Sequence[str], m, cov, held_terms, noise: float, tol: float,
          r: float, b_given: np.ndarray, reference=None) -> dict:
    """{name: entry} of the estimated core parameters that fail at the base fit ``fit`` (no
    added effect terms; see module doc; the Cramér–Rao error counts the information of
    ``reference``, :class:`~.reference_rows.ReferenceRows`, when given);
    entry: value, sigma (σ_p), sigma_fit, sigma_predicted, range, reason, score (sort key)."""
    if not free:
        return {}
    # a base fit: its only effect terms are the calibration's, held
    _, x, _, normal, D = project(fit.K, fit.b, list(held_terms), m, cov)
    A = jacobian(list(free), [], x, normal, D, cov, x @ fit.K.T, fit.K)
    if reference is not None:
        A = np.vstack([A, reference.information_rows(free, fit.K, fit.b, list(held_terms), m,
                                                     cov, max(noise, fit.sigma))])
    predicted = predicted_errors(A, max(noise, fit.sigma))
    out = {}
    for name, pred in zip(free, predicted):
        value, sd_fit = fit.estimated[name]
        sd = float(max(sd_fit, pred)) if np.isfinite(sd_fit) else float("inf")
        lo, hi = plausible_range(name, r, b_given)
        outside = max(lo - value, value - hi, 0.0)
        reasons = []
        if outside > SUSPICIOUS_SIGMAS * sd:
            reasons.append(f"outside the plausible range [{lo:.4g}, {hi:.4g}] by {outside:.3g} "
                           f"(> {SUSPICIOUS_SIGMAS:g} σ)")
        if not sd <= tol:
            reasons.append(f"σ {sd:.3g} at the fitted point above the tolerance {tol:.3g}")
        if reasons:
            score = (outside > SUSPICIOUS_SIGMAS * sd, sd / tol if np.isfinite(sd) else np.inf)
            out[name] = {"value": float(value), "sigma": sd, "sigma_fit": float(sd_fit),
                         "sigma_predicted": float(pred), "range": [lo, hi],
                         "reason": "; ".join(reasons), "score": score}
    return out


def settle(fit_with: Callable[[list], HeldFit], free: Sequence[str], m, cov, held_terms,
           noise: float, tol: float, r: float, b_given: np.ndarray,
           keep: Sequence[str] = (), reference=None) -> Settled:
    """Fit with ``fit_with(free)`` (started from the given calibration), re-check at the fitted
    point, hold the worst failing parameter not in ``keep`` and refit, until none fails
    (module doc). At most len(free) + 1 fits."""
    free = list(free)
    held_after, rounds = [], 0
    while True:
        # a fit drifting along an undetermined direction overflows on its way; the check
        # below is what catches it
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            fit = fit_with(free)
            failed = check(fit, free, m, cov, held_terms, noise, tol, r, b_given, reference)
        rounds += 1
        may_hold = {k: v for k, v in failed.items() if k not in keep}
        if not may_hold:
            suspicious = {k: _public(v) for k, v in failed.items()}
            return Settled(fit, free, rounds, held_after, suspicious)
        worst = max(may_hold, key=lambda k: may_hold[k]["score"])
        held_after.append({"parameter": worst, **_public(may_hold[worst])})
        free.remove(worst)


def _public(entry: dict) -> dict:
    return {k: v for k, v in entry.items() if k != "score"}
