"""Diagnose a recording against a calibration the user already holds (issue #10).

Flights, drives and warm-ups cover a slice of the sphere, which cannot determine a fresh K and
b. Here the base model is the *given* calibration: the parameters the slice determines
(:func:`streamcal.diagnosis.held.choose_free`, a Cramér–Rao error below a tolerance) are
re-estimated, the others held at the calibration's values; the candidate effects are fitted the
same way (held parameters stay held, the effect's θ is free) and ranked as in
:func:`streamcal.diagnosis.diagnose` (F test on common inliers, materiality, the noise floor).

Without a calibration the held values are a stated default: b from an algebraic sphere fit
re-estimated on the slice, K = r·I with r = median ‖m − b‖. b must then be determined
(refused otherwise, saying how many samples at this noise would do).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration, jsonable
from ..errors import InputError, InsufficientDataError, StreamcalError
from ..fitting.entries import B_PARAMS
from ..model import (REGISTRATION_EFFECTS, TERMS, build_effects, missing_columns,
                     terms_from_params)
from ..model.build import check_known
from . import candidates as cand
from . import misfit as misfit_mod
from . import verdict as verdict_mod
from .aux_channels import channel_scores
from .diagnosis import LADDER_STEPS, Diagnosis
from .held import (OUTLIER_WIDTHS, TOLERANCE, HeldFit, choose_free, core_params, field_radius,
                   held_fit, project)
from .gyro_pin import confirm, gyro_pin, pinned_model
from .effect_plausibility import implausible_effect, theta_sigmas
from .held_check import settle
from .noise import noise_floor
from .rank_subset import RANK_MAX, rank_subset
from .residuals import families
from .spans import outlier_spans

#: Fewest samples for any diagnosis against a calibration.
MIN_SAMPLES = 30
#: Default-calibration iterations (b on the slice, then r from it).
DEFAULT_ROUNDS = 3


@dataclass(repr=False)   # the short repr of Diagnosis, not every field
class HeldDiagnosis(Diagnosis):
    """A :class:`~streamcal.diagnosis.diagnosis.Diagnosis` against a given (or default)
    calibration: ``held`` names the parameters kept at their given values, ``estimated`` maps
    each re-estimated one to ``{"value", "sigma"}`` (sensor unit; σ from σ̂²(AᵀWA)⁻¹),
    ``predicted_sigma`` the Cramér–Rao error each had when chosen, ``tolerance`` the bound they
    were held to, ``calibration_source`` where the held values came from."""

    held: list = field(default_factory=list)
    estimated: dict = field(default_factory=dict)
    predicted_sigma: dict = field(default_factory=dict)
    tolerance: float = float("nan")
    calibration_source: str = ""
    unit: str = ""
    #: Samples the candidate refits (and ladder steps after the first) used; ``n`` when all.
    n_ranked: int = 0
    #: ``{channel: r}``: how closely the base model's residual (every sample) follows each
    #: auxiliary channel alone (:func:`streamcal.diagnosis.aux_channels.channel_scores`), largest first.
    aux_channels: dict = field(default_factory=dict)
    #: How the base (held) fit's LM loop ended: ``{"status", "iterations", "message"}``.
    fit_status: dict = field(default_factory=dict)
    #: Parameters held by the re-check at the fitted point
    #: (:func:`streamcal.diagnosis.held_check.settle`), in order, each with the value and σ it
    #: had and why; and ``suspicious``: kept parameters (b without a calibration) that failed it.
    held_after_fit: list = field(default_factory=list)
    suspicious: dict = field(default_factory=dict)
    #: Held parameters the gyro link pinned instead (:mod:`streamcal.diagnosis.gyro_pin`):
    #: ``{name: {"value", "sigma", "held_value"}}``; ``gyro_link`` how that was decided.
    gyro_pinned: dict = field(default_factory=dict)
    gyro_link: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        out = self._held_dict()
        out["n_ranked"] = int(self.n_ranked or self.n)
        out["aux_channels"] = dict(self.aux_channels)
        out["fit_status"] = dict(self.fit_status)
        out["held_after_fit"] = list(self.held_after_fit)
        out["suspicious"] = dict(self.suspicious)
        out["gyro_pinned"] = jsonable(self.gyro_pinned)
        out["gyro_link"] = jsonable(self.gyro_link)
        return out

    def candidate_dict(self, c) -> dict:
        """As for a fresh diagnosis; an implausible candidate
        (:func:`streamcal.diagnosis.effect_plausibility.implausible_effect`) is neither
        significant nor material, and ``implausible`` says why."""
        out = super().candidate_dict(c)
        why = getattr(c, "implausible", "")
        if why:
            out.update(significant=False, material=False, implausible=why)
        return out

    def _held_dict(self) -> dict:
        out = super().to_dict()
        out.update(held=list(self.held), estimated=self.estimated,
                   predicted_sigma=self.predicted_sigma, tolerance=self.tolerance, unit=self.unit,
                   calibration_source=self.calibration_source)
        return out


class _Eval:
    """One held fit evaluated like :class:`streamcal.diagnosis.diagnosis._Evaluated`."""

    def __init__(self, fit: HeldFit, cal: Calibration, p: int, terms=()):
        self.fit, self.cal, self.p, self.terms = fit, cal, p, list(terms)
        self.r, self.x, self.s, self.normal = fit.r, fit.x, fit.s, fit.normal
        self.inliers = fit.inliers
        self.rss = np.sum(fit.r ** 2, axis=1)
        self.rms = float(np.sqrt(np.mean(self.rss[self.inliers]))) if self.inliers.any() \
            else float("nan")


def default_calibration(m: np.ndarray, model: Sequence[str] = DEFAULT_MODEL) -> Calibration:
    """The stated default: b from the algebraic sphere fit ‖m‖² = 2 mᵀb + c, K = r·I with
    r = median ‖m − b‖ (sensor unit)."""
    A = np.column_stack([2 * m, np.ones(len(m))])
    sol, *_ = np.linalg.lstsq(A, np.sum(m * m, axis=1), rcond=None)
    b = sol[:3]
    r = float(np.median(np.linalg.norm(m - b, axis=1)))
    return Calibration(K=r * np.eye(3), b=b, model=tuple(model), method="default")


def _calibration(K, b, base: Calibration, terms, fit: HeldFit, model) -> Calibration:
    effects = dict(base.effects)
    for term, theta in terms:
        effects[term.name] = term.to_physical(theta, 1.0)
    return base.replace(K=K, b=b, model=tuple(model), effects=effects, inliers=fit.inliers,
                        weights=None, directions=fit.x,
                        extra={**dict(base.extra or {}), "tau": fit.tau})


#: Ridge of :func:`linear_start`, relative to each column's sum of squares.
RIDGE = 1e-2


def linear_start(term, s: np.ndarray, normal: np.ndarray, u: np.ndarray, cov,
                 tau: float) -> np.ndarray:
    """Starting θ for a candidate: least squares of the signed normal residual ``s`` (N,) on a
    constant and the columns nᵀ ∂f/∂θ (the effect's first-order change of s is −nᵀ ∂f/∂θ δθ),
    kept only when it lowers the linearised Cauchy cost (width ``tau``); else ``term.initial()``.

    Why: an effect of a few µT against a noise of 0.1 µT puts the samples it moves (the flight
    against the ground run, full throttle) beyond the Cauchy width, where their weight is
    ~(τ/s)²; a robust fit started at θ = 0 then calls them outliers and never explains them."""
    theta0 = np.asarray(term.initial(), float)
    Z = np.einsum("ni,nip->np", normal, term.jac_theta(theta0, u, cov))
    ok = np.all(np.isfinite(Z), axis=1) & np.isfinite(s)
    if ok.sum() <= Z.shape[1] + 1:
        return theta0
    A = np.column_stack([np.ones(int(ok.sum())), Z[ok]])
    # a light ridge: channels that move together (throttle, motor outputs) would otherwise get
    # large cancelling coefficients, far outside where the linearisation holds
    H = A.T @ A
    H[1:, 1:] += RIDGE * np.diag(np.diag(H[1:, 1:]) + 1e-300)
    coef = np.linalg.solve(H, A.T @ s[ok])
    after = s[ok] - coef[0] - Z[ok] @ coef[1:]
    if np.sum(np.log1p((after / tau) ** 2)) < np.sum(np.log1p((s[ok] / tau) ** 2)):
        return theta0 + coef[1:]
    return theta0


def _refuse_b(n: int, errors: dict, tol: float, unit: str, sigma: float) -> None:
    from ..units import display_unit

    unit = display_unit(unit)
    worst = max(errors.get(name, np.inf) for name, _ in B_PARAMS)
    if worst <= tol:
        return
    need = int(np.ceil(n * (worst / tol) ** 2)) if np.isfinite(worst) else None
    more = (f"about {need} samples at this noise ({sigma:.3g} {unit} per axis), " if need else "")
    raise InsufficientDataError(
        f"without a calibration the hard-iron offset b must come from this recording, but its "
        f"{n} samples predict it to ±{worst:.3g} {unit} (Cramér–Rao, noise {sigma:.3g} {unit}), "
        f"above the tolerance {tol:.3g} {unit} ({TOLERANCE:.1%} of the field radius). What "
        f"would answer it: {more}a wider range of directions, or a calibration you already "
        f"hold (--cal CAL.json)")


def diagnose_against(track, calibration: Calibration | None = None, *,
                     model: Sequence[str] = DEFAULT_MODEL, candidates: Sequence[str] | None = None,
                     ladder: bool = True, calibration_source: str | None = None,
                     tolerance: float = TOLERANCE, rank_max: int = RANK_MAX) -> HeldDiagnosis:
    """Diagnose ``track`` relative to ``calibration`` (None: the default of
    :func:`default_calibration`), holding what the recording does not determine.

    ``tolerance``: a parameter is re-estimated when its predicted error is below ``tolerance``
    × the field radius. Refuses (InsufficientDataError) with fewer than :data:`MIN_SAMPLES`
    samples, or, without a calibration, when b cannot be determined to that tolerance.
    Registration effects (gravity- and gyro-tied) are not ranked here.

    With more than ``rank_max`` samples the candidates are ranked on the subsample of
    :func:`streamcal.diagnosis.rank_subset.rank_subset` (every direction cell and stretch of
    time kept): each candidate's ``rms_before``/``rms_after`` and the ladder steps after the
    first are on it (``n_ranked`` samples); ``rms``, ``held``, ``estimated`` are on all."""
    m = np.asarray(track.mag, dtype=float)
    n = len(m)
    unit = track.mag_unit
    if n < MIN_SAMPLES:
        raise InsufficientDataError(f"{n} samples are too few to diagnose anything: at least "
                                    f"{MIN_SAMPLES} are needed (record longer)")
    t = np.asarray(track.t_mag, dtype=float)
    cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
    cov.setdefault("t", t)
    gyro = np.stack([cov[k] for k in ("gx", "gy", "gz")], 1) if all(
        k in cov for k in ("gx", "gy", "gz")) else None
    nf = noise_floor(m, t, gyro)
    sigma = float(np.sqrt(np.mean(np.square(nf.sigma_axes)))) if np.all(
        np.isfinite(nf.sigma_axes)) and np.any(nf.sigma_axes > 0) else float("nan")
    given = calibration is not None
    if given:
        if calibration.sensor != "mag":
            raise InputError(f"{calibration_source or 'calibration'}: a {calibration.sensor} "
                             "calibration cannot diagnose magnetometer readings")
        base_cal = calibration
        model = tuple(n_ for n_ in calibration.model if n_ not in REGISTRATION_EFFECTS)
        source = (calibration_source or dict(calibration.extra or {}).get("source")
                  or "given calibration")
    else:
        model = tuple(check_known(model))
        base_cal = default_calibration(m, model)
        source = ("default: b re-estimated from this recording, K = r·I with "
                  "r = median |m − b|")
    held_terms = terms_from_params(base_cal.effects)   # the calibration's effects, held
    names = core_params(model)
    K0, b0 = base_cal.K, base_cal.b
    tol = tolerance * field_radius(K0)
    if not np.isfinite(sigma) or sigma <= 0:
        sigma = float(np.median(np.abs(np.linalg.norm(m - b0, axis=1) - field_radius(K0))))
    b_names = [p for p, _ in B_PARAMS]
    keep = () if given else b_names   # without a calibration b is what is asked for
    free, errors = choose_free(names, K0, b0, m, cov, held_terms, sigma, tol, keep)
    if not given:
        _refuse_b(n, errors, tol, unit, sigma)
        for _ in range(DEFAULT_ROUNDS):   # b on the slice, r from it
            fit = held_fit(m, cov, K0, b0, b_names, held_terms)
            b0 = fit.b
            K0 = float(np.median(np.linalg.norm(m - b0, axis=1))) * np.eye(3)
        base_cal = base_cal.replace(K=K0, b=b0)
        tol = tolerance * field_radius(K0)
        free, errors = choose_free(names, K0, b0, m, cov, held_terms, sigma, tol, keep)
        _refuse_b(n, errors, tol, unit, sigma)

    def evaluate(new_terms, start=None, m_=m, cov_=cov):
        # candidates start from the model they extend (same held values, a lower cost)
        K_s, b_s = (K0, b0) if start is None else (start.fit.K, start.fit.b)
        fit = held_fit(m_, cov_, K_s, b_s, free, held_terms, new_terms, sigma)
        cal = _calibration(fit.K, fit.b, base_cal, list(zip([t for t, _ in new_terms],
                                                            fit.thetas)),
                           fit, (*model, *(t.name for t, _ in new_terms)))
        return _Eval(fit, cal, len(free) + sum(len(th) for th in fit.thetas),
                     [t for t, _ in new_terms])

    # re-check at the fitted point; the candidates then use the settled estimated set
    settled = settle(lambda f: held_fit(m, cov, K0, b0, f, held_terms, (), sigma), free, m, cov,
                     held_terms, sigma, tol, field_radius(K0), b0, keep)
    free = settled.free
    fit = settled.fit
    # held parameters the gyro link determines (only when that helps: gyro_pin's rules)
    pin = gyro_pin(track, m, t, cov, held_terms, fit, free,
                   [p for p in names if p not in free], tol, field_radius(K0))
    K0p, b0p = pinned_model(K0, b0, pin)
    again = confirm(pin, fit, lambda: settle(
        lambda f: held_fit(m, cov, K0p, b0p, f, held_terms, (), sigma), free, m, cov,
        held_terms, sigma, tol, field_radius(K0), b0, keep))
    if again is not None:
        K0, b0, settled, free, fit = K0p, b0p, again, again.free, again.fit
    base = _Eval(fit, _calibration(fit.K, fit.b, base_cal, [], fit, model), len(free), [])
    # the floor the verdict and the materiality test use: the same rule as a fresh diagnosis
    reliable, reason = verdict_mod.floor_reliable(nf.floor, nf.reliable, nf.reason, base.rms,
                                                  "sensor")
    floor = verdict_mod.reported_floor(nf.floor, reliable)
    idx = rank_subset(m, base.fit.b, t, rank_max)
    m_r, cov_r = (m, cov) if idx is None else (m[idx], {k: v[idx] for k, v in cov.items()})
    base_r = base if idx is None else evaluate([], base, m_r, cov_r)
    if candidates is None:
        names_c = [c for c in TERMS if c not in model and c not in base_cal.effects]
        absent = missing_columns(names_c, track)
        names_c = [c for c in names_c if c not in absent]
    else:
        names_c = [c for c in check_known(candidates) if c in TERMS and c not in model]

    radius = field_radius(K0)

    def rank(ref: _Eval, added: tuple, pool) -> list:
        out = []
        u_fit, u_cal = ref.x @ ref.fit.K.T, ref.x @ ref.cal.K.T     # the same for every candidate
        for name in pool:
            try:
                term = build_effects([name], cov_r)[0]
                prior = list(zip(ref.terms, ref.fit.thetas))
                start = linear_start(term, ref.s, ref.normal, u_fit, cov_r,
                                     ref.fit.tau)
                ev = evaluate([*prior, (term, start)], ref, m_r, cov_r)
                if np.any(start != term.initial()) and not ev.rms <= ref.rms * 10:
                    ev = evaluate([*prior, (term, term.initial())], ref, m_r, cov_r)
            except (StreamcalError, ValueError, np.linalg.LinAlgError):
                continue   # the data cannot support this effect (e.g. a constant channel)
            # over the samples either model counts as inliers: an effect of a few µT moves
            # whole segments (motors off on the ground) beyond the base model's Cauchy width,
            # and what it explains there would not show on the base model's inliers alone
            both = ref.inliers | ev.inliers
            before = float(np.sqrt(np.mean(ref.rss[both])))
            after = float(np.sqrt(np.mean(ev.rss[both])))
            p_value = cand.f_test(float(ref.rss[both].sum()), float(ev.rss[both].sum()),
                                  max(ev.p - ref.p, 1), cand.effective_n(ev.r[both]), ev.p)
            text = cand.evidence(name, term, ref.s, ref.normal, u_cal, cov_r, ref.inliers)
            c = cand.Candidate(name, after, p_value, text, ev.p - ref.p,
                               cand.is_significant(before, after, p_value, floor), ev.cal)
            c.rms_before, c.residual, c._evaluated = before, "sensor", ev
            c.n_compared = int(both.sum())
            c.implausible = implausible_effect(
                [(term, ev.fit.thetas[-1])], u_fit, cov_r, radius,
                theta_sigmas(ev.fit.estimated, name, term.n_params()))
            if c.implausible:
                c.significant, c.evidence = False, f"{c.implausible}; {c.evidence}"
            out.append(c)
        out.sort(key=lambda c: (not c.significant, c.rms_after / c.rms_before))
        return out

    ranked = rank(base_r, (), names_c)
    n_r = len(m_r)
    steps = [{"model": list(model), "rms": base.rms, "residual": "sensor", "n": n}]
    current, added, cur_ranked = base_r, (), ranked
    while ladder and cur_ranked and cur_ranked[0].significant and len(steps) <= LADDER_STEPS:
        top = cur_ranked[0]
        added, current = (*added, top.effect), top._evaluated
        steps.append({"model": [*model, *added], "added": top.effect, "rms": top.rms_after,
                      "rms_before": top.rms_before, "residual": "sensor",
                      "p_value": top.p_value, "gravity_tied": False, "gyro_tied": False,
                      "n": n_r})
        rest = [c.effect for c in cur_ranked[1:] if c.p_value < cand.P_VALUE]
        cur_ranked = rank(current, added, rest) if rest else []
    verdict = verdict_mod.decide(base.rms, "sensor", nf.floor, reliable, ranked)
    misfit = misfit_mod.localise(base.r, base.inliers, t, m - np.asarray(base.cal.b, float), cov,
                                 gyro)
    if current is base_r:
        current = base
    inl = current.inliers
    if len(inl) != n:   # a ladder model fitted on the subsample, judged on every sample
        r_all = project(current.fit.K, current.fit.b,
                        [*held_terms, *zip(current.terms, current.fit.thetas)], m, cov)[0]
        inl = np.linalg.norm(r_all, axis=1) <= OUTLIER_WIDTHS * current.fit.tau
    outliers = ~np.asarray(inl, bool)
    held = [p for p in names if p not in free and p not in pin.pinned] + [
        p for p in ("K_xx", "K_xy", "K_xz", "K_yy", "K_yz", "K_zz", "b_x", "b_y", "b_z")
        if p not in names] + [f"{t.name}" for t, _ in held_terms]
    estimated = {k: {"value": v, "sigma": e} for k, (v, e) in base.fit.estimated.items()}
    return HeldDiagnosis(
        model=tuple(model), n=n, n_outliers=int((~base.inliers).sum()),
        n_outliers_model=int(outliers.sum()), rms=base.rms, noise_floor=floor,
        noise_floor_reliable=reliable, noise_floor_reason=reason, misfit=misfit,
        verdict=verdict, candidates=ranked, outlier_spans=outlier_spans(t, outliers),
        ladder=steps, residual="sensor", outliers_model=(*model, *added), outliers=outliers,
        residual_families=families(base.cal, m, cov, base.inliers, base.r, base.x),
        noise={"sigma_axes": [float(v) for v in nf.sigma_axes], "lsb": [float(v) for v in nf.lsb],
               "method": nf.method, "n_used": nf.n_used},
        calibration=base.cal, held=held, estimated=estimated,
        predicted_sigma={k: errors[k] for k in names if k in errors}, tolerance=tol,
        calibration_source=source, unit=unit, n_ranked=n_r,
        aux_channels=channel_scores(base.s, base.normal, cov),
        fit_status={"status": base.fit.status, "iterations": base.fit.iterations,
                    "message": base.fit.message},
        held_after_fit=settled.held_after_fit, suspicious=settled.suspicious,
        gyro_pinned=pin.pinned, gyro_link=pin.report)
