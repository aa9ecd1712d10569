"""Is a candidate effect's refit physical? (issue #10, diagnosis against a given calibration)

A candidate refit on a slice of the sphere can drift to a θ that lowers the residual without
being the effect: a cubic gain of 0.0034 µT⁻² (a bend of 190 % of the field at a field radius
of 23 µT) fits the PXF flight's points better, and so does a gain of 10⁸ along an axis the
slice does not see. :func:`implausible_effect` marks a candidate as implausible by two rules:

1. **Size.** The rms over the recording's points of the effect's field ``f(θ, u)``, ``u`` the
   *base* model's field points (sensor unit), is above ``BOUND[kind] · r``, ``r`` the field
   radius of the given calibration. The bound per kind is declared with the effect (``bound`` of
   its :class:`~streamcal.model.declaration.EffectDeclaration`, the why beside it;
   docs/diagnose_against_calibration.md tabulates them); kinds that state none use the field
   radius itself.

   Why at the base model's points: a candidate that drifts to a degenerate θ fits its *own*
   points with a modest field; moved back to where the model without it puts the field, its
   field is that of the drift.

2. **Not determined.** θ is within its own errors of zero: Σₖ (θₖ/σₖ)² ≤ p (p = len θ, the
   mean of that sum if θ were 0), σₖ the refit's error of θₖ; or some σₖ is not finite. Such a
   θ is whatever the slice's free direction allowed, not a measurement of the effect.
"""
from __future__ import annotations

import numpy as np

from ...model.catalog import PLAUSIBILITY_BOUNDS
from ...model.declaration import DEFAULT_BOUND

#: ``BOUND[kind]``: largest plausible rms of an effect's field at the recording's points, as a
#: fraction of the field radius r, for every term effect (a view of the declarations). Kinds
#: not listed use :data:`DEFAULT_BOUND`.
BOUND = PLAUSIBILITY_BOUNDS


def theta_sigmas(estimated: dict, name: str, n: int) -> np.ndarray:
    """(n,) σ of the added effect ``name``'s θ from a held fit's ``estimated`` ({``name[k]``:
    (value, σ)}); NaN where missing."""
    return np.array([float(estimated.get(f"{name}[{k}]", (np.nan, np.nan))[1])
                     for k in range(n)])


def implausible_effect(terms_thetas, u: np.ndarray, cov, r: float, sigmas=None,
                       unit: str = "µT") -> str:
    """Why an added effect is implausible (module doc, rules 1 and 2), or "" when it is not.

    ``terms_thetas``: [(term, θ)] of the candidate (the first term names the kind); ``u`` (N,3)
    the base model's field points and ``r`` the field radius (sensor unit); ``sigmas``: the
    refit's σ of each θ, concatenated in the order of ``terms_thetas`` (rule 2 is skipped when
    None); ``unit``: the sensor unit as shown."""
    f = sum(np.asarray(term.term(th, u, cov), float) for term, th in terms_thetas)
    rms = float(np.sqrt(np.mean(np.sum(np.square(f), axis=1))))
    kind = terms_thetas[0][0].name
    frac = BOUND.get(kind, DEFAULT_BOUND)
    reasons = []
    if not (np.isfinite(rms) and rms <= frac * r):
        size = f"{rms:.3g} {unit}" if rms < 1e3 * r else "over 1000 × the field radius"
        reasons.append(f"its field at the reference model's points is {size} rms, above "
                       f"{frac:g} × the field radius {r:.3g} {unit} (the bound for {kind})")
    if sigmas is not None:
        theta = np.concatenate([np.ravel(th) for _, th in terms_thetas]).astype(float)
        sd = np.asarray(sigmas, dtype=float)
        if not np.all(np.isfinite(sd)) or not np.all(sd > 0):
            reasons.append("its parameters are not determined (their uncertainty is not finite)")
        else:
            chi2 = float(np.sum((theta / sd) ** 2))
            if not chi2 > len(theta):
                reasons.append(f"its parameters are not determined: they lie within their own "
                               f"uncertainty of zero (Σ(θ/σ)² = {chi2:.3g} for {len(theta)} "
                               f"parameters)")
    return ("implausible: " + "; ".join(reasons)) if reasons else ""
