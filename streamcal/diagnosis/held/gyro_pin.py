"""Pin held parameters with the gyro link, only where that helps (issue #10).

A slice leaves some parameters of K and b undetermined by the sphere (normal) residual; they are
held at the given calibration (:mod:`streamcal.diagnosis.held`). When the recording has a gyro,
the rotation between readings (:mod:`streamcal.fitting.gyro_link`, residual (1) there) can
observe some of them. The gyro estimate *replaces* the held value ("pinned") only when all of:

1. **the gyro explains the rotation**: on the link residual with the held values, the rms is at
   most :data:`EXPLAINED` × the rms of predicting each reading with no rotation (a gyro in
   another frame, saturated or very noisy fails);
2. **it is determined**: each pinned parameter's standard error is within the same tolerance
   as the sphere's re-estimated ones (TOLERANCE × r). Starting from every held parameter, the
   one with the largest predicted (Cramér–Rao, at the held point) error is left held until all
   are within it; the rest are fitted, and one whose error at the fitted point (block
   sandwich, see the fitting module) exceeds it is left held too and the rest refitted (so a
   rotation that does not observe a parameter leaves it held);
3. **it does not lean on a wrong held value** (:mod:`streamcal.diagnosis.gyro_guard`): fitted
   with every held parameter free, the link's estimate of the ones still held would not move
   the pinned values significantly (χ² test at p :data:`~streamcal.diagnosis.gyro_guard.P_GUARD`)
   and by more than their σ; each still-held value's difference from the link's is reported;
4. **it predicts held-out time better**: the pairs are cut into :data:`FOLDS` contiguous time
   blocks; for each, the link is fitted on the others with the candidate set free and with it
   held (the gyro's bias/gain free in both), and the held-out block's link residual is
   compared: the rms over the pairs either fit counts as inliers (‖r‖ ≤ 2 widths of the held
   fit) must be lower with the pinned values, pooled over the blocks;
5. **the sphere does not object** (checked by the caller, :mod:`streamcal.diagnosis.against`):
   refitted with the pinned values held, the sphere residual rms rises by at most
   :data:`SPHERE_RISE` (a rise means the sphere saw these parameters after all and disagrees).

Anything else leaves them held, and ``reason`` says which rule failed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ...constants import OUTLIER_WIDTHS
from ...errors import InsufficientDataError, MissingColumnsError
from ...fitting.gyro_lag import EXPLAINED
from ...fitting.gyro_rates import gyro_rates
from ...fitting.entries import entry, with_entries
from ...fitting.gyro_link import N_GYRO, LinkPairs, SpherePrior, link_fit, subset_errors
from .gyro_guard import RULE as GUARD_RULE
from .gyro_guard import disagreement, held_check
from .fit import jacobian, project
from ..residuals import rms

#: Rule 1: link rms at most EXPLAINED (gyro_lag's rule: the gyro explains the rotation) × the
#: no-rotation rms.
#: Rule 4: contiguous held-out time blocks.
FOLDS = 4
#: Rule 5: sphere rms with the pinned values at most this factor of the rms with them held.
SPHERE_RISE = 1.05
RULE = (f"pinned only when: the gyro explains the rotation (link rms ≤ {EXPLAINED:g} × the "
        f"no-rotation rms); each pinned σ ≤ the tolerance; {GUARD_RULE}; the link rms on "
        f"{FOLDS} held-out time blocks is lower than with the parameters held; the sphere rms "
        f"rises by at most {SPHERE_RISE - 1:.0%}")


@dataclass
class GyroPin:
    """``used``: the pinned values replace the held ones; ``pinned`` {name: {value, sigma,
    held_value}} (:func:`pinned_model` applies them); ``report`` the JSON-able summary (key
    ``gyro_link`` of the diagnosis)."""

    used: bool
    pinned: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)

    def reject(self, reason: str) -> "GyroPin":
        """The same outcome, not used, saying why."""
        self.report.update(used=False, reason=reason)
        self.used, self.pinned = False, {}
        return self


#: Joint fits: at most this many rounds; the sphere residual is re-linearised at each round's
#: estimate (a slice's valley between b and K is curved: one linearisation at a wrong held
#: value biases).
JOINT_ROUNDS = 4
#: Stop the joint rounds after one that moved every estimate by less than this many σ
#: (measured on the simulated slices: each round moves ~0.1× the previous one, so about
#: 0.02 σ is left).
JOINT_STOP = 0.2
#: Rounds of each held-out fit, started from the all-data joint estimate.
HELD_OUT_ROUNDS = 1


def sphere_prior(K, b, fit, names: Sequence[str], m, cov, held_terms) -> SpherePrior:
    """The sphere residual at ``K``, ``b`` linearised over the core parameters ``names``
    (F = AᵀWA/σ̂², c = AᵀWs/σ̂², W Cauchy weights of the width and σ̂ of the held fit
    ``fit``, :class:`streamcal.diagnosis.held.HeldFit`)."""
    _, x, s, normal, D = project(K, b, list(held_terms), m, cov)
    A = jacobian(list(names), [], x, normal, D, cov, x @ np.asarray(K).T, K)
    w = 1.0 / (1.0 + (s / fit.tau) ** 2)
    sig2 = max(fit.sigma, 1e-12) ** 2
    return SpherePrior(list(names), np.einsum("n,np,nq->pq", w, A, A) / sig2,
                       np.einsum("n,np,n->p", w, A, s) / sig2)


def gyro_pin(track, m: np.ndarray, t: np.ndarray, cov, held_terms, fit, free: Sequence[str],
             held: Sequence[str], tol: float, r: float) -> GyroPin:
    """Rules 1–4 of the module doc for the ``held`` core parameters of the model, at the
    settled sphere fit ``fit`` (HeldFit: K, b with the held values) whose re-estimated
    parameters are ``free``; ``cov`` the covariates at the readings, ``held_terms`` the
    calibration's effect terms; ``tol`` sensor unit; ``r`` the field radius. The held
    parameters are fitted jointly with the ``free`` ones, the link plus the linearised sphere
    residual (:func:`sphere_prior`), so a free parameter the wrong held value bent is bent back."""
    K, b = np.asarray(fit.K, float), np.asarray(fit.b, float)
    free = list(free)
    out = GyroPin(False, report={"used": False, "rule": RULE, "residual": "gyro_link",
                                       "tolerance": tol})
    if not held:
        return out.reject("no parameter is held")
    try:
        t_g, w_g = gyro_rates(track)
        pairs = LinkPairs(m, t, t_g, w_g)
    except MissingColumnsError:
        return out.reject("no gyro columns (gx, gy, gz)")
    except InsufficientDataError as exc:
        return out.reject(str(exc))
    out.report.update(n_pairs=len(pairs), horizon_s=pairs.horizon)
    names = list(held)
    base = link_fit(pairs, K, b, [], scale=r)
    out.report.update(rms_held=base.rms, rms_still=base.rms_still)
    if not base.rms <= EXPLAINED * base.rms_still:
        return out.reject(f"the gyro does not explain the rotation: link rms {base.rms:.3g} "
                          f"> {EXPLAINED:g} × the no-rotation rms {base.rms_still:.3g}")
    def prior_at(est, start=None):
        """The sphere prior over ``est`` at ``start``'s K, b (default the held point)."""
        Kc, bc = (K, b) if start is None else (start.K, start.b)
        return sphere_prior(Kc, bc, sfit, est, m, cov, held_terms)

    def joint(est, sel=None, start=None, rounds=JOINT_ROUNDS, prior=None):
        """``prior``: :func:`prior_at` (est, start), when the caller already has it."""
        Kc, bc = (K, b) if start is None else (start.K, start.b)
        for _ in range(rounds):
            if prior is None:
                prior = sphere_prior(Kc, bc, sfit, est, m, cov, held_terms)
            f = link_fit(pairs, Kc, bc, est, sel=sel, scale=r, sphere=prior)
            moved = max((abs(f.estimated[n_][0] - entry(Kc, bc, n_)) / f.estimated[n_][1]
                         for n_ in est), default=0.0)
            Kc, bc, prior = f.K, f.b, None
            if moved < JOINT_STOP:   # the next linearisation point would barely move
                break
        return f

    sfit = fit
    # choose on the information at the held point (Cramér–Rao errors of each subset from one
    # evaluation), then fit the chosen set; one whose sandwich error at the fitted point is
    # above the tolerance is dropped and the rest refitted
    allp = [*free, *names]
    prior_all = prior_at(allp)
    start = link_fit(pairs, K, b, allp, scale=r, rounds=0, sphere=prior_all)
    gyro = list(range(len(allp), len(allp) + N_GYRO))
    tried = {}
    while names:
        keep = [allp.index(n_) for n_ in [*free, *names]] + gyro
        sd = dict(zip([*free, *names], subset_errors(start, keep)))
        for n_ in names:
            tried[n_] = {"value": entry(K, b, n_), "sigma_predicted": float(sd[n_])}
        worst = max(names, key=lambda n_: sd[n_])
        if sd[worst] <= tol:
            fit = joint([*free, *names], prior=prior_all if len(names) == len(held) else None)
            worst = max(names, key=lambda n_: fit.estimated[n_][1])
            for n_ in names:
                tried[n_].update(value=fit.estimated[n_][0], sigma=fit.estimated[n_][1])
            if fit.estimated[worst][1] <= tol:
                break
        names.remove(worst)
    out.report["estimates"] = tried
    if not names:
        return out.reject("the rotation does not determine any held parameter within the "
                          f"tolerance {tol:.3g} (σ: " + ", ".join(
                              f"{k} {v.get('sigma', v['sigma_predicted']):.3g}"
                          for k, v in tried.items()) + ")")
    # rule 3 (the guard) before the held-out folds: it is the cheaper (one joint fit, none
    # when every held parameter is a candidate) and refuses the misleading case
    all_fit = fit if len(names) == len(held) else joint(allp, prior=prior_all)
    guard = held_check(all_fit, allp, names, {h: entry(K, b, h) for h in held},
                       {n_: fit.estimated[n_][1] for n_ in names})
    guard["unconditional"] = {n_: list(all_fit.estimated[n_]) for n_ in names}
    out.report.update(candidates=list(names), guard=guard)
    if not guard["passed"]:
        return out.reject(disagreement(guard))
    held_ho, pinned_ho = _held_out(pairs, free, names, joint, prior_at, fit)
    out.report.update(candidates=list(names), rms_heldout_held=held_ho,
                      rms_heldout_pinned=pinned_ho, rms_link=fit.rms)
    if not pinned_ho < held_ho:
        return out.reject(f"held-out link rms not lower with the gyro's values "
                          f"({pinned_ho:.4g} vs {held_ho:.4g} held)")
    out.used = True
    out.pinned = {n_: {"value": fit.estimated[n_][0], "sigma": fit.estimated[n_][1],
                       "held_value": entry(K, b, n_)} for n_ in names}
    out.report.update(used=True, reason="every rule passed")
    return out


def _held_out(pairs: LinkPairs, free, names, joint, prior_at,
              pinned_fit) -> tuple[float, float]:
    """Pooled held-out link rms (rule 4) with ``names`` held and fitted (``free`` fitted in
    both, by ``joint(est, sel, start, rounds, prior)``: the sphere residual from every reading,
    the link from the training blocks; each started from the all-data estimate,
    :data:`HELD_OUT_ROUNDS` rounds). The sphere prior at a start, ``prior_at(est, start)``,
    does not depend on the fold: built once per start."""
    starts = (joint(list(free)) if free else None, pinned_fit)
    variants = list(zip((list(free), [*free, *names]), starts))
    priors = [prior_at(est, start) for est, start in variants]
    t_pair = pairs.t[pairs.a]
    edges = np.quantile(t_pair, np.linspace(0, 1, FOLDS + 1))
    fold = np.clip(np.searchsorted(edges, t_pair, side="right") - 1, 0, FOLDS - 1)
    sq_h, sq_p = [], []
    for k in range(FOLDS):
        test = np.flatnonzero(fold == k)
        # a pair straddling the boundary shares readings with the test block: left out
        train = np.flatnonzero((fold != k) & ((pairs.t[pairs.b] < edges[k]) |
                                              (t_pair > edges[k + 1])))
        res = []
        for (est, start), prior in zip(variants, priors):
            f = joint(est, train, start, HELD_OUT_ROUNDS, prior)
            R = pairs.rotations(f.gyro_bias, f.gyro_gain)[test]
            res.append((np.linalg.norm(pairs.residual(f.K, f.b, R, test), axis=1), f.tau))
        (rh, tau), (rp, _) = res
        keep = (rh <= OUTLIER_WIDTHS * tau) | (rp <= OUTLIER_WIDTHS * tau)
        sq_h.append(rh[keep] ** 2)
        sq_p.append(rp[keep] ** 2)
    return (float(np.sqrt(np.mean(np.concatenate(sq_h)))),
            float(np.sqrt(np.mean(np.concatenate(sq_p)))))


def pinned_model(K, b, pin: GyroPin) -> tuple[np.ndarray, np.ndarray]:
    """The given model ``K``, ``b`` with the pinned values substituted (copies)."""
    return with_entries(K, b, list(pin.pinned), [e["value"] for e in pin.pinned.values()])


def confirm(pin: GyroPin, held_fit_, refit: Callable):
    """Rule 5: ``refit()`` (the settled sphere fit with the pinned values held) against
    ``held_fit_`` (with them at the given values). Returns the refit when it passes, else None
    (and ``pin`` says why)."""
    if not pin.used:
        return None
    new = refit()
    before, after = rms(held_fit_.r, held_fit_.inliers), rms(new.fit.r, new.fit.inliers)
    pin.report.update(sphere_rms_held=before, sphere_rms_pinned=after)
    if not after <= SPHERE_RISE * before:
        pin.reject(f"the sphere rms rose from {before:.4g} to {after:.4g} with the gyro's "
                   f"values (more than {SPHERE_RISE - 1:.0%})")
        return None
    return new
