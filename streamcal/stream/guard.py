"""Acceptance guard: a candidate calibration replaces the one in use only if it is sane and better.

Sane: finite rms no larger than a fraction of the field; field strength (the geometric mean radius
of ``K``, ``|det K|^(1/3)``) within physical limits for the unit (15–100 µT for the Earth's
field anywhere, 8–11.6 m/s² for gravity), or, for other units, within a ratio of a reference
radius (the running sphere estimate); offset ``‖b‖`` within limits; condition number of ``K``
within limits (a strongly anisotropic ``K`` is a fit to a sliver of the sphere, not soft iron).

Better: on held-out samples (not used in the candidate's fit) the candidate's error is not larger
than the error of the calibration in use, beyond what the sample size can resolve. Both are
evaluated on the same samples, so the comparison is paired: per sample ``a_i`` (candidate) and
``c_i`` (in use) are ``|‖K⁻¹(m − b)‖ − 1|`` times the calibration's radius (sensor unit); the
10 % of samples with the largest ``max(a_i, c_i)`` are dropped (a magnet passing the board during
the held-out samples must not decide); the candidate is accepted when
``mean(a) ≤ mean(c) + max(tolerance · mean(c), 2 · se(a − c))``. Every decision names its rule,
the value and the limit it was compared with.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Physical field strength limits per unit: Earth field 22–67 µT at the surface (IGRF), gravity.
FIELD_LIMITS = {"uT": (15.0, 100.0), "m/s^2": (8.0, 11.6)}
#: Largest plausible offset ‖b‖ per unit (a board's hard iron; the AK8963 range is ±4912 µT).
OFFSET_LIMITS = {"uT": 1000.0, "m/s^2": 5.0}
#: Minimum held-out samples for a comparison.
MIN_HOLDOUT = 5


@dataclass(frozen=True)
class Decision:
    """The guard's verdict: ``reason`` names the rule; ``value`` was compared with ``limit``."""

    accepted: bool
    reason: str
    value: float | None = None
    limit: float | None = None
    details: dict = field(default_factory=dict)
    #: Sensor unit of ``value`` and ``limit`` when they are a field, an offset or an rms.
    unit: str | None = None

    def __str__(self) -> str:
        verdict = "accepted" if self.accepted else "rejected"
        return f"{verdict}: {self.explain()}"

    def explain(self) -> str:
        """The rule and how the value compares with its limit, in words and units:
        ``field_out_of_range: field 1.82 µT is below the lower limit 15 µT``."""
        from ..units import display_unit, number

        if self.value is None:
            return self.reason
        what, unit = _SUBJECTS.get(self.reason, ("value", False))
        u = (" " + display_unit(self.unit)) if unit and self.unit else ""
        value = f"{what} {number(self.value, 4)}{u}"
        if self.limit is None:
            return f"{self.reason}: {value}"
        limit = f"{number(self.limit, 4)}{u}"
        if self.value < self.limit:
            side = "below the lower limit" if self.reason == "field_out_of_range" else \
                "below the limit"
        elif self.value > self.limit:
            side = "above the upper limit" if self.reason == "field_out_of_range" else \
                "above the limit"
        else:
            side = "at the limit"
        return f"{self.reason}: {value} is {side} {limit}"

    def text(self) -> str:
        """The rule and its figures in words (no verdict)."""
        if self.value is None:
            return self.reason
        if self.limit is None:
            return f"{self.reason} = {self.value:.4g}"
        return f"{self.reason}: {self.value:.4g} vs limit {self.limit:.4g}"

    def to_dict(self) -> dict:
        return {"accepted": self.accepted, "reason": self.reason, "value": _num(self.value),
                "limit": _num(self.limit), **{k: _num(v) for k, v in self.details.items()}}


#: What ``value`` is for each rule, and whether it is in the sensor unit.
_SUBJECTS = {
    "field_out_of_range": ("field", True), "offset_too_large": ("offset |b|", True),
    "ill_conditioned": ("condition number of K", False), "rms_too_large": ("rms", True),
    "rms_grew": ("rms", True), "too_few_holdout": ("held-out samples", False),
    "holdout_not_finite": ("finite held-out samples", False),
    "first_calibration": ("held-out error", True),
    "current_broken_on_holdout": ("held-out error", True),
    "better_on_holdout": ("held-out error", True), "worse_on_holdout": ("held-out error", True),
    "parameters_not_finite": ("field", True), "rms_not_finite": ("rms", True),
}


def _num(v):
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def holdout_errors(cal, m: np.ndarray, covariates: dict | None = None) -> np.ndarray:
    """Per-sample error (n,) of ``cal`` on samples ``m`` (n,3), sensor unit:
    ``|‖K⁻¹(m − b)‖ − 1|`` times the calibration's radius."""
    x = apply_finite(cal, m, covariates)
    return np.abs(np.linalg.norm(x, axis=1) - 1.0) * cal.radius


def apply_finite(cal, m: np.ndarray, covariates: dict | None = None) -> np.ndarray:
    """``cal.apply(m, covariates)`` (n,3), NaN on the rows where a covariate is not finite (a
    calibration with temperature or aux terms while that channel was never seen): its effect
    terms cannot be evaluated there."""
    if not cal.effects:
        return np.linalg.solve(cal.K, (m - cal.b).T).T
    cov = covariates or {}
    ok = np.ones(len(m), dtype=bool)
    for v in cov.values():
        ok &= np.isfinite(np.asarray(v, dtype=float))
    if ok.all():
        return cal.apply(m, cov)
    x = np.full(np.shape(m), np.nan)
    if ok.any():
        x[ok] = cal.apply(m[ok], {k: np.asarray(v)[ok] for k, v in cov.items()})
    return x


def holdout_error(cal, m: np.ndarray, covariates: dict | None = None) -> float:
    """Mean of :func:`holdout_errors` over the finite ones after dropping the largest 10 %."""
    e = holdout_errors(cal, m, covariates)
    e = np.sort(e[np.isfinite(e)])
    return float(e[:max(1, int(np.ceil(0.9 * len(e))))].mean()) if len(e) else float("nan")


def _paired(a: np.ndarray, c: np.ndarray) -> tuple[float, float, float, int]:
    """Trimmed means of ``a`` and ``c`` and the standard error of their difference."""
    ok = np.isfinite(a) & np.isfinite(c)
    a, c = a[ok], c[ok]
    keep = np.argsort(np.maximum(a, c))[:max(1, int(np.ceil(0.9 * len(a))))]
    a, c = a[keep], c[keep]
    se = float(np.std(a - c, ddof=1) / np.sqrt(len(a))) if len(a) > 1 else float("inf")
    return float(a.mean()), float(c.mean()), se, len(a)


class AcceptanceGuard:
    """Decide whether a candidate calibration may replace the one in use.

    Args:
        max_cond: largest condition number of ``K``.
        max_rms_ratio: largest ``rms / radius``.
        field_ratio: allowed radius / reference radius for units without physical limits.
        offset_ratio: largest ``‖b‖ / radius`` for units without physical limits.
        tolerance: relative slack of the held-out comparison (held-out errors are noisy; a
            candidate within it of the one in use is not worse).
    """

    def __init__(self, *, max_cond: float = 5.0, max_rms_ratio: float = 0.25,
                 field_ratio: tuple[float, float] = (0.5, 2.0), offset_ratio: float = 20.0,
                 tolerance: float = 0.02, field_limits: dict | None = None,
                 offset_limits: dict | None = None, max_rms_growth: float = 2.0):
        self.max_cond = max_cond
        self.max_rms_growth = max_rms_growth
        self.max_rms_ratio = max_rms_ratio
        self.field_ratio = field_ratio
        self.offset_ratio = offset_ratio
        self.tolerance = tolerance
        self.field_limits = FIELD_LIMITS if field_limits is None else field_limits
        self.offset_limits = OFFSET_LIMITS if offset_limits is None else offset_limits

    def sanity(self, cand, reference_radius: float | None = None) -> Decision | None:
        """The first sanity rule ``cand`` breaks, as a rejection, or None when it is sane."""
        R = cand.radius
        if not (math.isfinite(cand.rms) and cand.rms >= 0):
            return Decision(False, "rms_not_finite", cand.rms, None)
        if not np.all(np.isfinite(cand.K)) or not np.all(np.isfinite(cand.b)) or not R > 0:
            return Decision(False, "parameters_not_finite", R, None)
        if cand.unit in self.field_limits:
            lo, hi = self.field_limits[cand.unit]
            if not lo <= R <= hi:
                return Decision(False, "field_out_of_range", R, lo if R < lo else hi,
                                unit=cand.unit)
        elif reference_radius:
            lo, hi = (f * reference_radius for f in self.field_ratio)
            if not lo <= R <= hi:
                return Decision(False, "field_out_of_range", R, lo if R < lo else hi,
                                unit=cand.unit)
        offset = float(np.linalg.norm(cand.b))
        limit = self.offset_limits.get(cand.unit, self.offset_ratio * R)
        if offset > limit:
            return Decision(False, "offset_too_large", offset, limit, unit=cand.unit)
        cond = float(np.linalg.cond(cand.K))
        if cond > self.max_cond:
            return Decision(False, "ill_conditioned", cond, self.max_cond)
        if cand.rms > self.max_rms_ratio * R:
            return Decision(False, "rms_too_large", cand.rms, self.max_rms_ratio * R,
                            unit=cand.unit)
        return None

    def check(self, cand, holdout_m: np.ndarray, holdout_cov: dict | None = None,
              current=None, reference_radius: float | None = None) -> Decision:
        """Decide on ``cand`` given held-out samples ``holdout_m`` (n,3) not used in its fit and
        the calibration in use ``current`` (or the coarse sphere estimate before the first)."""
        bad = self.sanity(cand, reference_radius)
        if bad is not None:
            return bad
        n = int(np.isfinite(holdout_m).all(axis=1).sum())
        if n < MIN_HOLDOUT:
            return Decision(False, "too_few_holdout", float(n), float(MIN_HOLDOUT))
        a = holdout_errors(cand, holdout_m, holdout_cov)
        if not np.isfinite(a).sum() >= MIN_HOLDOUT:
            return Decision(False, "holdout_not_finite", float(np.isfinite(a).sum()),
                            float(MIN_HOLDOUT))
        if current is None:
            return Decision(True, "first_calibration", holdout_error(cand, holdout_m, holdout_cov),
                            None, {"n_holdout": n}, unit=cand.unit)
        c = holdout_errors(current, holdout_m, holdout_cov)
        if np.isfinite(c).sum() < MIN_HOLDOUT:
            return Decision(True, "current_broken_on_holdout", holdout_error(
                cand, holdout_m, holdout_cov), None, {"n_holdout": n}, unit=cand.unit)
        cur_rms = float(getattr(current, "rms", float("nan")))
        if math.isfinite(cur_rms) and cur_rms > 0 and cand.rms > self.max_rms_growth * cur_rms:
            # A fit that no longer reaches the noise floor of the one in use was bent by a
            # disturbance or by samples of two environments; held-out samples may be mixed too.
            return Decision(False, "rms_grew", cand.rms, self.max_rms_growth * cur_rms,
                            unit=cand.unit)
        err, ref, se, used = _paired(a, c)
        limit = ref + max(self.tolerance * ref, 2.0 * se)
        details = {"n_holdout": used, "current_error": ref}
        if err <= limit:
            return Decision(True, "better_on_holdout", err, limit, details, unit=cand.unit)
        return Decision(False, "worse_on_holdout", err, limit, details, unit=cand.unit)
