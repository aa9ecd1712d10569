"""Diagnose a recording against a calibration the user already holds (or a stated default),
and refine that calibration with an effect: the held starting point
(:class:`streamcal.diagnosis.held.start.HeldStart`) under the one story of
:mod:`streamcal.diagnosis.story` (candidates on the samples the model with them keeps, the
ladder on the samples its last model keeps, each winner refitted on every sample)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration
from ..errors import InputError, StreamcalError
from ..model import TERMS, missing_columns
from ..units import display_unit
from ..model.build import check_known
from ..fitting.outlier_rule import outlier_spans
from . import candidates as cand
from . import misfit as misfit_mod
from . import story
from . import verdict as verdict_mod
from .held.aux_channels import channel_scores
from .diagnosis import LADDER_STEPS
from .result import Diagnosis
from .held.part import HeldPart
from .held.plausibility import implausible_effect, theta_sigmas
from .held.fit import TOLERANCE
from .held.start import HeldEval, HeldStart
from .held.rank_subset import RANK_MAX, rank_subset
from .residuals import families


def _candidate_names(start: HeldStart, candidates) -> list[str]:
    if candidates is None:
        names = [c for c in TERMS if c not in start.model and c not in start.base_cal.effects]
        absent = missing_columns(names, start.track)
        return [c for c in names if c not in absent]
    return [c for c in check_known(candidates) if c in TERMS and c not in start.model]


def _rank(start: HeldStart, ref: HeldEval, pool, floor: float, rows) -> list:
    """Each effect of ``pool`` added to ``ref`` (fitted on ``rows``, None: every sample) and
    compared with it on the samples the model with it keeps; best first."""
    out = []
    u_fit = ref.x @ ref.fit.K.T
    for name in pool:
        try:
            ev = start.add(name, ref, rows)
        except (StreamcalError, ValueError, np.linalg.LinAlgError):
            continue   # the data cannot support this effect (e.g. a constant channel)
        out.append(_candidate(start, name, ref, ev, floor, u_fit, rows))
    out.sort(key=lambda c: (not c.significant, c.rms_after / c.rms_before))
    return out


def _candidate(start: HeldStart, name: str, ref: HeldEval, ev: HeldEval, floor: float, u_fit,
               rows) -> cand.Candidate:
    cov = start.cov_at(rows)
    numbers = story.compare(ref, ev)
    term = ev.terms[-1]
    text = cand.evidence(name, term, ref.s, ref.normal, ref.x @ ref.cal.K.T, cov, ref.inliers)
    implausible = implausible_effect(
        [(term, ev.fit.thetas[-1])], u_fit, cov, start.radius,
        theta_sigmas(ev.fit.estimated, name, term.n_params()),
        display_unit(start.unit) or "sensor units")
    significant = not implausible and cand.is_significant(numbers.before, numbers.after,
                                                          numbers.p_value, floor)
    return cand.Candidate(name, numbers.after, numbers.p_value,
                          f"{implausible}; {text}" if implausible else text, ev.p - ref.p,
                          significant, ev.cal, residual="sensor", rms_before=numbers.before,
                          n=numbers.n, implausible=implausible, _evaluated=ev, _reference=ref)


def _on_every_sample(start: HeldStart, c: cand.Candidate, ref: HeldEval,
                     floor: float) -> cand.Candidate:
    """The candidate ``c`` (ranked on a subsample) refitted on every sample on top of ``ref``
    (every sample too), so that what it promises is what ``streamcal fit --cal`` gives."""
    ev = start.add(c.effect, ref)
    return _candidate(start, c.effect, ref, ev, floor, ref.x @ ref.fit.K.T, None)


def diagnose_against(track, calibration: Calibration | None = None, *,
                     model: Sequence[str] = DEFAULT_MODEL, candidates: Sequence[str] | None = None,
                     ladder: bool = True, calibration_source: str | None = None,
                     tolerance: float = TOLERANCE, rank_max: int = RANK_MAX,
                     location: dict | None = None, attitude: bool = True) -> Diagnosis:
    """Diagnose ``track`` relative to ``calibration`` (None: the stated default of
    :func:`streamcal.diagnosis.held.start.default_calibration`), holding what the recording
    does not determine (:class:`~streamcal.diagnosis.held.start.HeldStart` says how and when
    it refuses); the result's ``held`` (a :class:`~streamcal.diagnosis.held.part.HeldPart`)
    says what was held and what re-estimated. Registration effects (gravity- and gyro-tied)
    are not ranked here.

    With more than ``rank_max`` samples the candidates are ranked on the subsample of
    :func:`streamcal.diagnosis.held.rank_subset.rank_subset` (every direction cell and stretch of
    time kept; each candidate's ``n`` says how many samples its numbers are over); each effect
    the ladder adds is refitted on every sample, and the ladder is on every sample.

    Where ``track`` has an attitude and a place (``location``, else its GPS) every held fit
    also fits the direction against the attitude reference (:mod:`.held.reference_rows`;
    ``attitude=False``: the magnitude alone); the result's ``held.attitude_reference`` says
    over which samples."""
    start = HeldStart(track, calibration, model=model, calibration_source=calibration_source,
                      tolerance=tolerance,
                      reference=_reference(track, calibration, location, attitude))
    base, nf, m, t, cov = start.base, start.nf, start.m, start.t, start.cov
    n = len(m)
    reliable, reason = verdict_mod.floor_reliable(nf.floor, nf.reliable, nf.reason, base.rms,
                                                  "sensor")
    floor = verdict_mod.reported_floor(nf.floor, reliable)
    idx = rank_subset(m, base.fit.b, t, rank_max)
    base_r = base if idx is None else start.evaluate([], base, idx)
    ranked = _rank(start, base_r, _candidate_names(start, candidates), floor, idx)
    def current(added):   # the model the ladder has reached, fitted on every sample
        return added[-1]._evaluated if added else base

    def on_every_sample(top, added):
        return top if idx is None else _on_every_sample(start, top, current(added), floor)

    def rank_after(added, rest):
        ev = added[-1]._evaluated
        ref_r = ev if idx is None else start.evaluate(list(zip(ev.terms, ev.fit.thetas)), ev,
                                                      idx)
        return _rank(start, ref_r, rest, floor, idx)

    def judge(c):
        return cand.is_significant(c.rms_before, c.rms_after, c.p_value, floor) \
            and not c.implausible

    added = story.climb_supported(ranked, rank_after, max_steps=LADDER_STEPS if ladder else 0,
                                  model=start.model, base=base, residual_of=lambda ev: "sensor",
                                  judge=judge, on_every_sample=on_every_sample)
    steps, added, ranked = story.tell(start.model, base, lambda ev: "sensor", added, ranked,
                                      judge)
    verdict = verdict_mod.decide(steps[0]["rms"], "sensor", nf.floor, reliable, ranked)
    misfit = misfit_mod.localise(base.r, base.inliers, t, m - np.asarray(base.cal.b, float), cov,
                                 start.gyro)
    outliers = ~np.asarray(current(added).inliers, bool)
    pin, names = start.pin, start.names
    held = [p for p in names if p not in start.free and p not in pin.pinned] + [
        p for p in ("K_xx", "K_xy", "K_xz", "K_yy", "K_yz", "K_zz", "b_x", "b_y", "b_z")
        if p not in names] + [f"{term.name}" for term, _ in start.held_terms]
    estimated = {k: {"value": v, "sigma": e} for k, (v, e) in base.fit.estimated.items()}
    return Diagnosis(
        model=tuple(start.model), n=n, n_outliers=steps[0]["n_outliers"],
        n_outliers_model=int(outliers.sum()), rms=steps[0]["rms"], noise_floor=floor,
        noise_floor_reliable=reliable, noise_floor_reason=reason, misfit=misfit,
        verdict=verdict, candidates=ranked, outlier_spans=outlier_spans(t, outliers),
        ladder=steps, residual="sensor",
        outliers_model=(*start.model, *(c.effect for c in added)), outliers=outliers,
        residual_families=families(base.cal, m, cov, base.inliers, base.r, base.x),
        noise={"sigma_axes": [float(v) for v in nf.sigma_axes], "lsb": [float(v) for v in nf.lsb],
               "method": nf.method, "n_used": nf.n_used},
        calibration=base.cal, unit=start.unit,
        last_calibration=current(added).cal if added else None, held=HeldPart(
            parameters=held, estimated=estimated,
            predicted_sigma={k: start.errors[k] for k in names if k in start.errors},
            tolerance=start.tol, calibration_source=start.source,
            n_ranked=n if idx is None else len(idx),
            aux_channels=channel_scores(base.s, base.normal, cov),
            fit_status={"status": base.fit.status, "iterations": base.fit.iterations,
                        "message": base.fit.message},
            held_after_fit=start.settled.held_after_fit, suspicious=start.settled.suspicious,
            gyro_pinned=pin.pinned, gyro_link=pin.report,
            attitude_reference=_described(start)))


def _reference(track, calibration, location, attitude: bool):
    """The attitude reference's rows for the held fit (:func:`.held.reference_rows.
    reference_rows`), None without one or when ``attitude`` is False."""
    if not attitude:
        return None
    from .held.reference_rows import reference_rows

    return reference_rows(track, calibration, location)[0]


def _described(start: HeldStart) -> dict:
    return {} if start.reference is None else start.reference.describe()


def _without_effects(cal: Calibration, names: Sequence[str]) -> Calibration:
    """``cal`` without the effects ``names`` (model and parameters)."""
    drop = [n for n in names if n in cal.model or n in cal.effects]
    if not drop:
        return cal
    return cal.replace(model=tuple(n for n in cal.model if n not in drop),
                       effects={k: v for k, v in cal.effects.items() if k not in drop})


def refine(track, calibration: Calibration | None, add: Sequence[str], *,
           calibration_source: str | None = None, tolerance: float = TOLERANCE,
           location: dict | None = None, attitude: bool = True) -> Calibration:
    """``calibration`` (None: the stated default) refined on ``track`` with the effects ``add``
    (in order): what the
    recording determines re-estimated, the rest held — the fit a held diagnosis promises
    (``streamcal fit TRACK --cal CAL --add EFFECT``). An effect of ``add`` that ``calibration``
    already carries (an autopilot's motor compensation in force) is fitted afresh, not kept
    at the calibration's values. The result's ``extra["held"]`` lists the held parameters; its
    rms and inliers follow the one outlier rule. With an attitude and a place (``location``,
    else the track's GPS) the held fit also fits the direction against the attitude reference,
    as :func:`diagnose_against` does; ``extra["attitude_reference_used"]`` then says over which
    samples."""
    reference = _reference(track, calibration, location, attitude)
    if calibration is not None:
        calibration = _without_effects(calibration, [n for n in check_known(add) if n in TERMS])
    start = HeldStart(track, calibration, calibration_source=calibration_source,
                      tolerance=tolerance, reference=reference)
    names = [n for n in check_known(add) if n not in start.model]
    bad = [n for n in names if n not in TERMS]
    if bad:
        raise InputError(f"--add {', '.join(bad)}: a calibration held where the recording "
                         f"cannot determine it is refined only with "
                         f"{', '.join(TERMS)}")
    absent = missing_columns(names, track)
    if absent:
        raise InputError(f"--add {', '.join(absent)}: the recording lacks the columns "
                         f"{', '.join(', '.join(v) for v in absent.values())}")
    ev = start.base
    for name in names:
        ev = start.add(name, ev)
    held = [p for p in start.names if p not in ev.free and p not in start.pin.pinned]
    used = {"attitude_reference_used": _described(start)} if start.reference is not None else {}
    return ev.cal.replace(extra={**dict(ev.cal.extra or {}), "held": held,
                                 "refined_from": start.source, **used})
