"""``diagnose``: compare the fitted model with the measurements, find where it fails and which
effect is missing (docs/cli.md ``streamcal diagnose``)."""
from __future__ import annotations

import inspect
from typing import Callable, Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL, RESIDUALS
from . import story
from ..errors import StreamcalError
from ..model import REGISTRATION_EFFECTS, TERMS, build_effects, check_needs, missing_columns
from ..model.build import check_known
from ..fitting.registration import RTOL, gravity_reference, registration_fit
from . import candidates as cand
from . import misfit as misfit_mod
from . import verdict as verdict_mod
from .noise import noise_floor
from .tied_noise import tied_floor
from .residuals import families, rms, sensor_residual
from .result import Diagnosis
from ..fitting.outlier_rule import outlier_mask, outlier_spans

#: Candidate refits for the ranking use at most this many well-spread samples.
SUBSET_MAX = 6000
#: The gravity-tied ranking refits (on the spread subset) stop once an LM step lowers the robust
#: cost by less than this, relative (the full fits: ``registration.RTOL``). Their rms is within
#: ~0.3 % of the converged one (the 1-hour bench track), the ranking is by rms ratios of 0.6-0.9,
#: and the winner is refitted on every sample to full tolerance (issue #13 item 2).
QUICK_TIED_RTOL = 1e-4
#: Most effects the ladder adds.
LADDER_STEPS = 3
#: ``_Evaluated.kind`` → the residual family (:data:`streamcal.calibration.RESIDUALS`, in its
#: order: sensor, gravity-tied, gyro-tied) named in the JSON.
RESIDUAL_OF_KIND = dict(zip((None, "gravity", "gyro"), RESIDUALS))
#: How each residual family is called in text and pictures.
RESIDUAL_LABELS = {"sensor": "sensor", "gravity_tied": "gravity-tied", "gyro_tied": "gyro-tied"}


def _default_fitter(kernel: str) -> Callable:
    def fit(track, model, initial=None):
        from ..fitting import fit as _fit

        return _fit(track, model=tuple(model), kernel=kernel, initial=initial)
    return fit


def _candidate_names(model: Sequence[str], track) -> list[str]:
    names = [n for n in (*TERMS, *REGISTRATION_EFFECTS) if n not in model]
    if "soft_iron" not in model:
        names.insert(0, "soft_iron")
    if "hard_iron" not in model:
        names.insert(0, "hard_iron")
    missing = missing_columns(names, track)
    # mag_accel_misalignment needs the accelerometer; time_lag the accelerometer (gravity-tied)
    # or the gyro (gyro-tied, streamcal.fitting.gyro_lag).
    return [n for n in names if n not in missing]


def _tied(model) -> bool:
    return any(n in REGISTRATION_EFFECTS for n in model)


class _Evaluated:
    """One fitted model with its residuals (eq. 41, or the gravity- or gyro-tied residual of
    :mod:`streamcal.fitting.registration` / :mod:`streamcal.fitting.gyro_lag` when ``reg`` is
    given) and inlier set."""

    def __init__(self, cal, m, cov, floor, reg=None):
        t = cov.get("t") if cov is not None else None
        self.cal, self.tied = cal, reg is not None
        #: which residual: None (eq. 41), "gravity" or "gyro" (the tied residuals).
        self.kind = None if reg is None else (
            "gyro" if "gyro_tied" in (reg.calibration.extra or {}) else "gravity")
        self.reg = reg
        if reg is not None:
            self.r, self.x = reg.residuals, reg.directions
            self.s = self.normal = None
            self.inliers = np.asarray(reg.inliers, bool)
            self.p = reg.n_params
        else:
            self.r, self.x, self.s, self.normal = sensor_residual(cal, m, cov)
            norm = np.linalg.norm(self.r, axis=1)
            inl = getattr(cal, "inliers", None)
            width = (getattr(cal, "extra", None) or {}).get("tau")
            if inl is None or np.shape(inl) != (len(m),):
                # a fit on a subset, or without a kernel: the one outlier rule on every sample
                inl = ~outlier_mask(norm, width, t, floor)
                if hasattr(cal, "replace"):
                    cal = cal.replace(inliers=inl, n_outliers=int((~inl).sum()),
                                      rms=rms(self.r, inl), n=len(m))
            self.cal = cal
            self.inliers = np.asarray(inl, bool)
            self.p = cand.n_global_params(cal)
        self.rms = rms(self.r, self.inliers)
        self.rss = np.sum(self.r ** 2, axis=1)


class _Context:
    """What every refit of one diagnosis shares: the track, its arrays, the fitter and the
    gravity reference (built once, on demand)."""

    def __init__(self, track, fitter, kernel, floor, subset_max=None, gravity=None, cov=None):
        self.track, self.fitter, self.floor = track, fitter, floor
        #: the floor the materiality test uses: NaN once the floor is found unmeasurable
        self.material_floor = floor
        #: (K, reliable, reason) the tied floors are computed with, once the base is fitted
        self._tied_basis = None
        self.tied_floors = {}
        # the tied fits have one robust cost of their own (as streamcal.fit does for them)
        self.kernel = "cauchy" if kernel == "auto" else kernel
        self.m = np.asarray(track.mag, dtype=float)
        cov = track.covariates_at_mag() if cov is None else cov
        self.cov = {k: np.asarray(v, dtype=float) for k, v in cov.items()}
        self.cov.setdefault("t", np.asarray(track.t_mag, dtype=float))
        self._gref = gravity
        self._gyro = {}
        self._warm = "initial" in inspect.signature(fitter).parameters
        self.subset = None    # (mag sample indices, sub-track) for the ranking refits
        if subset_max and len(self.m) > subset_max:
            from ..fitting.ellipsoid import spread_subset

            idx = spread_subset(self.m, subset_max)
            keep = ~np.asarray(track.mag_rows, bool)
            keep[np.flatnonzero(track.mag_rows)[idx]] = True
            self.subset = (idx, track.select(keep))

    def set_floor(self, floor: float, reliable: bool, reason: str, K) -> None:
        """The magnetometer floor as judged once the base model's rms is known (``floor``
        NaN when not ``reliable``) and the base calibration's ``K``, which the tied floors
        scale the reference's error by."""
        self.material_floor = floor
        self._tied_basis = (np.asarray(K, float), reliable, reason)

    def floor_for(self, residual: str) -> float:
        """The floor (sensor unit, NaN when not measurable) a rms on ``residual`` is judged
        against: the magnetometer's, or the tied residual's own
        (:mod:`streamcal.diagnosis.tied_noise`, computed once)."""
        if residual == "sensor":
            return self.material_floor
        if residual not in self.tied_floors:
            K, reliable, reason = self._tied_basis
            gravity = self.gref if residual == "gravity_tied" and self.track.has("accel") \
                else None
            self.tied_floors[residual] = tied_floor(residual, self.track, K, self.floor,
                                                    reliable, reason, gravity=gravity)
        entry = self.tied_floors[residual]
        return entry.floor if entry.reliable else float("nan")

    def gyro_fit(self, model, initial=None, *, fit_lag=False, lag=0.0, quick=True):
        """Gyro-tied fit (:func:`streamcal.fitting.gyro_lag.gyro_lag_fit`) of the non-registration
        part of ``model`` (plus ``time_lag`` when ``fit_lag``; else τ = ``lag``), fitted on the
        pairs starting in the spread subset when ``quick``; cached. None when the track has no
        gyro or the data cannot support the fit."""
        try:
            return self._gyro_fit(model, initial, fit_lag, lag, quick)
        except StreamcalError:
            return None

    def _gyro_fit(self, model, initial, fit_lag, lag, quick):
        """:meth:`gyro_fit`, raising the fit's error (cached too)."""
        names = tuple(n for n in model if n not in REGISTRATION_EFFECTS)
        quick = quick and self.subset is not None
        key = (names, fit_lag, float(lag), quick)
        if key not in self._gyro:
            from ..fitting.gyro_lag import gyro_lag_fit

            try:
                self._gyro[key] = gyro_lag_fit(
                    self.track, (*names, "time_lag") if fit_lag else names, kernel=self.kernel,
                    initial=initial, lag=lag, rows=self.subset[0] if quick else None)
            except StreamcalError as exc:
                self._gyro[key] = exc
        if isinstance(self._gyro[key], StreamcalError):
            raise self._gyro[key]
        return self._gyro[key]

    def gyro_lag(self, model, initial=None):
        """The lag (s) fitted on the gyro-tied residual alone, or None."""
        return self.gyro_fit(model, initial, fit_lag=True)

    @property
    def built_gref(self):
        """The gravity reference given or built so far (None: none was needed)."""
        return self._gref

    @property
    def gref(self):
        if self._gref is None:
            self._gref = gravity_reference(self.track)
        return self._gref

    def evaluate(self, model, initial=None, *, tied=False, quick=False) -> _Evaluated:
        """Fit ``model`` (warm-started from ``initial``) and evaluate it on every sample;
        ``tied`` forces the gravity-tied fit even without a registration effect (the
        registration base); ``quick`` fits on the spread subset only (see :func:`diagnose`)."""
        gyro_tied = not self.track.has("accel") and self.track.has("gyro") and \
            "mag_accel_misalignment" not in model
        if (tied or _tied(model)) and gyro_tied:   # shares the cache of the gyro family
            reg = self._gyro_fit(model, initial, "time_lag" in model, 0.0, quick)
            return _Evaluated(reg.calibration, self.m, self.cov, self.floor, reg)
        if tied or _tied(model):
            rows = self.subset[0] if quick and self.subset is not None else None
            gref = self.gref if self.track.has("accel") else None   # else gyro-tied
            reg = registration_fit(self.track, model, kernel=self.kernel, initial=initial,
                                   gref=gref, rows=rows,
                                   rtol=QUICK_TIED_RTOL if rows is not None else RTOL)
            return _Evaluated(reg.calibration, self.m, self.cov, self.floor, reg)
        track = self.subset[1] if quick and self.subset is not None else self.track
        if self._warm and initial is not None:
            cal = self.fitter(track, model, initial=initial)
        else:
            cal = self.fitter(track, model)
        if track is not self.track:
            cal = cal.replace(inliers=None, weights=None, directions=None)
        return _Evaluated(cal, self.m, self.cov, self.floor)


def _rank(ctx: _Context, base: _Evaluated, model, names) -> list:
    """Refit ``model`` + each of ``names`` and rank them. A registration candidate is compared
    with the gravity-tied fit of ``model`` (``base`` itself when it is tied already)."""
    out = []
    tied_base = base if base.tied else None
    for name in names:
        ref = base
        try:
            if name in REGISTRATION_EFFECTS and not base.tied:
                if tied_base is None:
                    tied_base = ctx.evaluate(model, base.cal, tied=True, quick=True)
                ref = tied_base
            ev = ctx.evaluate((*model, name), base.cal, quick=True)
        except StreamcalError:
            continue  # the data cannot support this effect (e.g. a constant temperature)
        numbers = story.compare(ref, ev)   # on the samples the model with it keeps
        if name in REGISTRATION_EFFECTS:
            text = _registration_text(ctx, model, base, name, numbers.before, ev)
        elif base.s is not None:
            term = build_effects([name], ctx.cov)[0] if name in TERMS else None
            text = cand.evidence(name, term, base.s, base.normal, base.x @ base.cal.K.T, ctx.cov,
                                 base.inliers)
        else:
            text = f"{ev.kind}-tied rms {numbers.before:.3g} → {numbers.after:.3g} {ctx.track.mag_unit}"
        out.append(_candidate(ctx, name, numbers, text, ref, ev))
    # rms_after of registration candidates is on the gravity-tied scale: rank by the ratio to
    # the rms each was compared with (the same order as rms_after among the others).
    out.sort(key=lambda c: (not c.significant, c.rms_after / c.rms_before))
    # The winner is refitted on every sample from the fit's own start — what `streamcal fit
    # --add` does, so its promise is exact (a warm start can settle elsewhere when many samples
    # are outliers); a registration winner that is no longer significant then drops behind the
    # significant ones (a stable sort), and the new winner is refitted in turn.
    refitted, tied_full = set(), None
    while out and out[0].effect not in refitted:
        top = out[0]
        refitted.add(top.effect)
        try:
            ev = ctx.evaluate((*model, top.effect))
        except StreamcalError:
            return out
        ref = top._reference
        if top.effect in REGISTRATION_EFFECTS and not base.tied:
            # compare like with like: the tied model without the effect refitted on every
            # sample too (its subset fit, evaluated on every sample, is a little worse)
            if tied_full is None:
                try:
                    tied_full = ctx.evaluate(model, base.cal, tied=True)
                except StreamcalError:
                    tied_full = False
            ref = tied_full or ref
        out[0] = top = _candidate(ctx, top.effect, story.compare(ref, ev), top.evidence, ref, ev)
        if top.effect not in REGISTRATION_EFFECTS:
            break
        out[0] = top.replace(evidence=_registration_text(ctx, model, base, top.effect,
                                                         top.rms_before, ev))
        out.sort(key=lambda c: not c.significant)
    return out


def _candidate(ctx: _Context, name: str, numbers, text: str, ref: _Evaluated,
               ev: _Evaluated) -> cand.Candidate:
    """A ranked candidate from its :class:`~streamcal.diagnosis.story.Comparison`."""
    return cand.Candidate(
        name, numbers.after, numbers.p_value, text, ev.p - ref.p,
        cand.is_significant(numbers.before, numbers.after, numbers.p_value,
                            ctx.floor_for(RESIDUAL_OF_KIND[ev.kind])),
        ev.cal, residual=RESIDUAL_OF_KIND[ev.kind], rms_before=numbers.before, n=numbers.n,
        _evaluated=ev, _reference=ref)


def _registration_text(ctx: _Context, model, base: _Evaluated, name: str, rms_before: float,
                       ev: _Evaluated) -> str:
    """Evidence for a registration candidate; a gravity-tied time lag adds the lag the gyro
    alone fits (cached by the context, so asking again costs nothing)."""
    text = cand.registration_evidence(name, rms_before, ev.rms, ev.cal, ctx.track.mag_unit,
                                      ev.kind)
    if name == "time_lag" and ev.kind == "gravity":
        gyro = ctx.gyro_lag(model, base.cal)
        if gyro is not None:   # the gyro's own view of the same lag
            text += f"; the gyro alone says {1e3 * gyro.lag:.1f} ms"
    return text


def _families(ctx: _Context, base: _Evaluated, model) -> dict:
    """Residual families of the base model (eq. 41 of its calibration when it is tied) and the
    gyro-consistency family at the model's lag, with the lag the gyro alone would fit."""
    if base.tied:
        r, x, inliers = None, None, np.asarray(base.cal.inliers, bool)
    else:
        r, x, inliers = base.r, base.x, base.inliers
    lag = float((base.cal.effects.get("time_lag") or {}).get("tau", 0.0))
    gyro = base.reg if base.kind == "gyro" else ctx.gyro_fit(model, base.cal, lag=lag)
    if gyro is not None:
        estimate = gyro if gyro is base.reg and "time_lag" in model else \
            ctx.gyro_lag(model, base.cal)
        gyro.lag_estimate = None if estimate is None else estimate.lag
    return families(base.cal, ctx.m, ctx.cov, inliers, r, x, gyro=gyro)


def diagnose(track, model: Sequence[str] = DEFAULT_MODEL, *, calibration=None,
             fitter: Callable | None = None, kernel: str = "auto",
             candidates: Sequence[str] | None = None, ladder: bool = True,
             subset_max: int | None = SUBSET_MAX, gravity=None) -> Diagnosis:
    """Diagnose ``model`` on ``track`` (a :class:`streamcal.inputs.track.Track`).

    ``gravity``: the :class:`~streamcal.fitting.gravity.GravityReference` of the track when
    it cannot be built from the track's rows as one stretch (a long recording's subsample:
    :mod:`streamcal.diagnosis.subsample` builds it on the stretches it read); None builds it.
    ``calibration``: an existing fit of ``model`` to use instead of fitting; ``fitter(track,
    model) -> Calibration`` replaces :func:`streamcal.fitting.fit`; ``candidates`` restricts the effects
    tried (default: every catalog effect the track supports that the model lacks); ``ladder``
    keeps adding the best significant effect (up to :data:`LADDER_STEPS`) and records the rms
    after each. ``kernel``: as :func:`streamcal.fitting.fit` (default ``auto``, so the rms here and
    ``streamcal fit``'s agree; the gravity- and gyro-tied fits use Cauchy for ``auto``, as
    ``fit`` does for them).

    Speed: every refit is warm-started from the model it extends (``fitter(track, model,
    initial=cal)`` when the fitter takes ``initial``). With more than ``subset_max`` samples the
    candidates are refitted on a well-spread subset of that size
    (:func:`streamcal.fitting.ellipsoid.spread_subset`) and evaluated on every sample (residual,
    inliers by the fit's own 2-kernel-width rule); the winner of each ranking is then refitted on
    every sample, so the top candidate's ``rms_after`` is exactly "add it and refit". None
    refits every candidate on every sample.

    Registration candidates are judged on the gravity-tied residual, or for ``time_lag`` on a
    track with a gyro and no accelerometer on the gyro-tied one (see
    :mod:`streamcal.diagnosis.candidates`). ``residual_families["gyro"]`` is the gyro-tied
    residual at the model's lag, with the lag the gyro alone fits (``lag_estimate_s``).

    ``n_outliers`` and ``rms`` are the base model's (``rms`` over its own inliers);
    ``outlier_spans``, ``outliers`` and ``n_outliers_model`` come from the last
    magnetometer-only model of the ladder (``outliers_model``). Every rms says which residual it
    is on (see :class:`Diagnosis`).
    """
    model = check_known(calibration.model if calibration is not None else model)
    check_needs(model, track)
    fitter = fitter or _default_fitter(kernel)
    m = np.asarray(track.mag, dtype=float)
    t = np.asarray(track.t_mag, dtype=float)
    cov0 = track.covariates_at_mag()
    gyro = np.stack([cov0[k] for k in ("gx", "gy", "gz")], 1) if all(
        k in cov0 for k in ("gx", "gy", "gz")) else None
    nf = noise_floor(m, t, gyro)
    ctx = _Context(track, fitter, kernel, nf.floor, subset_max, gravity, cov0)
    cov = ctx.cov
    base = (_Evaluated(calibration, m, cov, nf.floor) if calibration is not None and not _tied(model)
            else ctx.evaluate(model, calibration))
    residual = RESIDUAL_OF_KIND[base.kind]
    reliable, reason = verdict_mod.floor_reliable(nf.floor, nf.reliable, nf.reason, base.rms,
                                                  residual)
    floor = verdict_mod.reported_floor(nf.floor, reliable)
    ctx.set_floor(floor, reliable, reason, base.cal.K)
    names = _candidate_names(model, track) if candidates is None else [
        n for n in check_known(candidates) if n not in model]
    ranked = _rank(ctx, base, model, names)

    def rank_after(added, rest):
        return _rank(ctx, added[-1]._evaluated, (*model, *(c.effect for c in added)), rest)

    def judge(c):
        return cand.is_significant(c.rms_before, c.rms_after, c.p_value,
                                   ctx.floor_for(c.residual))

    def residual_of(ev):
        return RESIDUAL_OF_KIND[ev.kind]

    added = story.climb_supported(ranked, rank_after, max_steps=LADDER_STEPS if ladder else 0,
                                  model=model, base=base, residual_of=residual_of, judge=judge)
    spans = [(c._evaluated, (*model, *(a.effect for a in added[:k + 1])))
             for k, c in enumerate(added) if not c._evaluated.tied]
    spans_from, spans_model = spans[-1] if spans else (base, tuple(model))
    steps, added, ranked = story.tell(model, base, residual_of, added, ranked, judge)
    judged = ctx.floor_for(residual)   # the floor of the residual the rms is on
    verdict = verdict_mod.decide(steps[0]["rms"], residual, judged, bool(np.isfinite(judged)),
                                 ranked)
    misfit = misfit_mod.localise(base.r, base.inliers, t, m - np.asarray(base.cal.b, float),
                                 ctx.cov, gyro)
    # Spans and mask from the last magnetometer-only model of the ladder: a missing effect
    # makes the base model's residual large wherever the effect is (e.g. far from T0) — not
    # outliers.
    outliers = ~np.asarray(spans_from.inliers, bool)
    return Diagnosis(
        model=tuple(model), n=len(m), n_outliers=steps[0]["n_outliers"],
        n_outliers_model=int(outliers.sum()), rms=steps[0]["rms"],
        noise_floor=floor, verdict=verdict, candidates=ranked,
        noise_floor_reliable=reliable, noise_floor_reason=reason, misfit=misfit,
        noise_floor_rule=verdict_mod.floor_rule(residual),
        tied_noise_floors={k: v.to_dict() for k, v in ctx.tied_floors.items()},
        outlier_spans=outlier_spans(t, outliers), ladder=steps,
        residual=RESIDUAL_OF_KIND[base.kind], outliers_model=spans_model, outliers=outliers,
        residual_families=_families(ctx, base, model),
        noise={"sigma_axes": [float(v) for v in nf.sigma_axes], "lsb": [float(v) for v in nf.lsb],
               "method": nf.method, "n_used": nf.n_used, "measured": nf.measured,
               "second_difference_corr": nf.d2_corr},
        calibration=base.cal, unit=track.mag_unit, gravity=ctx.built_gref)
