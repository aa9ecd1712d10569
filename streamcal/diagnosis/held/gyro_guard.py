"""Guard of the gyro link: are the values still held consistent with the link? (issue #10)

A value pinned by the gyro link (:mod:`streamcal.diagnosis.gyro_pin`) is fitted with the other
held parameters fixed at the given calibration, so it is conditional on them: when one of them
is wrong, the link can pin the value that compensates for it, with a small σ, and pass every
other rule (measured: K_yz pinned 1.2 µT from the truth, 6.7 σ, while b_x and b_y were held
2 µT off).

The check (a Hausman-type test): the link plus the sphere residual is fitted once more with
*every* held parameter free (the joint fit of :func:`gyro_pin`), giving the link's own estimate
ĥ ± σ of each still-held parameter (σ = inf where the link and the sphere cannot see it). At
that fit, linearised, holding the still-held parameters at their given values h₀ instead moves
the pinned values by

    d = A (h₀ − ĥ),    A = −H_cc⁻¹ H_ch                                             (1)

(H the information of the joint fit, c the pinned, re-estimated and gyro-nuisance parameters,
h the still-held ones with finite σ). Were the held values right, h₀ − ĥ would be noise with
the covariance Σ_hh of the joint fit (block sandwich), and d would have the covariance
C = A Σ_hh Aᵀ. The pin is refused when χ² = dᵀ C⁻¹ d exceeds the (1 − :data:`P_GUARD`)
quantile of χ² with one degree per pinned value **and** some pinned value moves by more than
:data:`MATERIAL` × its own σ (a significant but immaterial shift leaves the pinned value
within its error). Each still-held parameter's held − link difference is reported
(``held_check``): that is the gyro's word on the held value.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.stats import chi2

from ...fitting.gyro_link import NULL_RATIO, LinkFit, pseudo_inverse

#: Significance of the shift test (1).
P_GUARD = 0.003
#: A pinned value must move by more than this many of its σ for the shift to matter.
MATERIAL = 1.0
RULE = (f"the pinned values would not move significantly (χ² test at p {P_GUARD:g}) and by "
        f"more than {MATERIAL:g} σ were the still-held parameters set to the link's joint "
        f"estimate")


def held_check(joint: LinkFit, names: Sequence[str], pinned: Sequence[str],
               held_values: dict, pinned_sigma: dict) -> dict:
    """The check of the module doc. ``joint``: the link fit over ``names`` (every re-estimated
    and held core parameter, in its vector order, then the gyro's nuisances) with its
    ``bread`` and ``meat``; ``pinned`` the names to pin, ``held_values`` {name: held value}
    of every held one (pinned or not), ``pinned_sigma`` {name: σ} of the pinned values from
    the conditional fit (sensor unit). Returns a JSON-able dict: ``passed``, ``chi2``,
    ``dof``, ``p_value``, ``shift`` {pinned name: −d, the move were the still-held set to the
    link's estimate}, ``held_check`` {still-held name:
    {held_value, link_value, link_sigma, difference, z}} and ``unseen`` (still-held names
    with σ = inf, not checked)."""
    names = list(names)
    n = len(joint.bread)
    still = [h for h in held_values if h not in pinned]
    check, seen = {}, []
    for h in still:
        value, sd = joint.estimated[h]
        diff = held_values[h] - value
        check[h] = {"held_value": float(held_values[h]), "link_value": float(value),
                    "link_sigma": float(sd), "difference": float(diff),
                    "z": float(diff / sd) if np.isfinite(sd) and sd > 0 else float("nan")}
        if np.isfinite(sd):
            seen.append(h)
    out = {"passed": True, "held_check": check, "unseen": [h for h in still if h not in seen],
           "shift": {}, "chi2": 0.0, "dof": 0, "p_value": 1.0}
    if not seen:
        return out
    hi = [names.index(h) for h in seen]
    ci = [k for k in range(n) if k not in hi]
    pi = [ci.index(names.index(p)) for p in pinned]
    H = joint.bread
    A = -pseudo_inverse(H[np.ix_(ci, ci)])[0] @ H[np.ix_(ci, hi)]
    Hinv = pseudo_inverse(H)[0]
    cov = Hinv @ joint.meat @ Hinv
    S_hh = cov[np.ix_(hi, hi)]
    dh = np.array([check[h]["difference"] for h in seen])
    d = (A @ dh)[pi]
    C = (A @ S_hh @ A.T)[np.ix_(pi, pi)]
    ev, V = np.linalg.eigh(C)
    keep = ev > max(ev[-1], 1e-300) * NULL_RATIO
    z = V[:, keep].T @ d
    stat = float(np.sum(z ** 2 / ev[keep]))
    dof = int(keep.sum())
    p = float(chi2.sf(stat, dof)) if dof else 1.0
    material = any(abs(dv) > MATERIAL * pinned_sigma[nm] for nm, dv in zip(pinned, d))
    out.update(shift={nm: -float(dv) for nm, dv in zip(pinned, d)}, chi2=stat, dof=dof,
               p_value=p, passed=not (p < P_GUARD and material))
    return out


#: Still-held parameters at least this many σ from the link's estimate are named.
NAMED_Z = 2.0


def disagreement(check: dict) -> str:
    """The refusal of a failed :func:`held_check`, naming the held values the gyro disagrees
    with (|z| ≥ :data:`NAMED_Z`, else the largest |z|) as "held at X, the link says Y ± σ"."""
    rows = sorted(((h, c) for h, c in check["held_check"].items() if np.isfinite(c["z"])),
                  key=lambda hc: -abs(hc[1]["z"]))
    named = [hc for hc in rows if abs(hc[1]["z"]) >= NAMED_Z] or rows[:1]
    said = "; ".join(f"{h} held at {c['held_value']:.4g} is off by {c['difference']:+.3g} ± "
                     f"{c['link_sigma']:.2g} (the link says {c['link_value']:.4g}, "
                     f"{c['z']:+.1f} σ)" for h, c in named)
    moved = ", ".join(f"{k} by {v:+.3g}" for k, v in check["shift"].items())
    return (f"the gyro disagrees with held values the pinned ones depend on: {said}; held at "
            f"the link's values they would move {moved} (χ² {check['chi2']:.3g}, "
            f"{check['dof']} dof, p {check['p_value']:.2g} < {P_GUARD:g})")
