"""``diagnose``: compare the fitted model with the measurements, find where it fails and which
effect is missing (SPEC §4 ``streamcal diagnose``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL
from ..errors import StreamcalError
from ..model import TERMS, build_effects, check_needs, missing_columns
from ..model.build import check_known
from . import candidates as cand
from .noise import noise_floor
from .residuals import families, rms, sensor_residual
from .spans import outlier_spans

#: Without robust weights from the fit, a sample is an outlier beyond this many noise σ.
OUTLIER_SIGMAS = 5.0
#: Most effects the ladder adds.
LADDER_STEPS = 3


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`; ``to_dict`` gives the JSON of SPEC §4 plus ``ladder``,
    ``noise`` and ``residual_families``. rms, noise_floor and rms_after in the sensor unit."""

    model: tuple[str, ...]
    n: int
    n_outliers: int
    rms: float
    noise_floor: float
    verdict: str
    candidates: list
    outlier_spans: list
    ladder: list = field(default_factory=list)
    residual_families: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)
    calibration: object = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {"model": list(self.model), "n": self.n, "n_outliers": self.n_outliers,
                "rms": self.rms, "noise_floor": self.noise_floor, "verdict": self.verdict,
                "candidates": [c.to_dict() for c in self.candidates],
                "outlier_spans": self.outlier_spans, "ladder": self.ladder, "noise": self.noise,
                "residual_families": self.residual_families}


def _default_fitter(kernel: str) -> Callable:
    def fit(track, model):
        from ..fit import fit as _fit

        return _fit(track, model=tuple(model), kernel=kernel)
    return fit


def _candidate_names(model: Sequence[str], track) -> list[str]:
    names = [n for n in TERMS if n not in model]
    if "soft_iron" not in model:
        names.insert(0, "soft_iron")
    if "hard_iron" not in model:
        names.insert(0, "hard_iron")
    missing = missing_columns(names, track)
    return [n for n in names if n not in missing]


class _Evaluated:
    """One fitted model with its eq. 41 residuals and inlier set."""

    def __init__(self, cal, m, cov, floor):
        self.cal = cal
        self.r, self.x, self.s, self.normal = sensor_residual(cal, m, cov)
        norm = np.linalg.norm(self.r, axis=1)
        inl = getattr(cal, "inliers", None)
        if inl is None or np.shape(inl) != (len(m),):
            scale = floor if np.isfinite(floor) else np.median(norm) / 0.6745
            inl = norm <= OUTLIER_SIGMAS * scale
        self.inliers = np.asarray(inl, bool)
        self.rms = rms(self.r, self.inliers)
        self.rss = np.sum(self.r ** 2, axis=1)
        self.p = cand.n_global_params(cal)


def _rank(base: _Evaluated, model, names, fitter, track, m, cov, floor) -> list:
    out = []
    for name in names:
        try:
            ev = _Evaluated(fitter(track, (*model, name)), m, cov, floor)
        except StreamcalError:
            continue  # the data cannot support this effect (e.g. a constant temperature)
        common = base.inliers & ev.inliers
        p_value = cand.f_test(float(base.rss[common].sum()), float(ev.rss[common].sum()),
                              max(ev.p - base.p, 1), int(common.sum()), ev.p)
        term = build_effects([name], cov)[0] if name in TERMS else None
        text = cand.evidence(name, term, base.s, base.normal, base.x @ base.cal.K.T, cov, base.inliers)
        c = cand.Candidate(name, ev.rms, p_value, text, ev.p - base.p,
                           cand.is_significant(base.rms, ev.rms, p_value, floor), ev.cal)
        c._evaluated = ev
        out.append(c)
    out.sort(key=lambda c: (not c.significant, c.rms_after))
    return out


def diagnose(track, model: Sequence[str] = DEFAULT_MODEL, *, calibration=None,
             fitter: Callable | None = None, kernel: str = "cauchy",
             candidates: Sequence[str] | None = None, ladder: bool = True) -> Diagnosis:
    """Diagnose ``model`` on ``track`` (a :class:`streamcal.track.Track`).

    ``calibration``: an existing fit of ``model`` to use instead of fitting; ``fitter(track,
    model) -> Calibration`` replaces :func:`streamcal.fit.fit`; ``candidates`` restricts the effects
    tried (default: every catalog effect the track supports that the model lacks); ``ladder``
    keeps adding the best significant effect (up to :data:`LADDER_STEPS`) and records the rms
    after each.
    """
    model = check_known(calibration.model if calibration is not None else model)
    check_needs(model, track)
    fitter = fitter or _default_fitter(kernel)
    m = np.asarray(track.mag, dtype=float)
    cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
    t = cov.get("t", np.asarray(track.t_mag, dtype=float))
    cov.setdefault("t", t)
    gyro = np.stack([cov[k] for k in ("gx", "gy", "gz")], 1) if all(
        k in cov for k in ("gx", "gy", "gz")) else None
    nf = noise_floor(m, t, gyro)
    base = _Evaluated(calibration if calibration is not None else fitter(track, model), m, cov, nf.floor)
    names = _candidate_names(model, track) if candidates is None else [
        n for n in check_known(candidates) if n not in model]
    ranked = _rank(base, model, names, fitter, track, m, cov, nf.floor)
    steps = [{"model": list(model), "rms": base.rms}]
    current, cur_model, cur_ranked = base, tuple(model), ranked
    while ladder and cur_ranked and cur_ranked[0].significant and len(steps) <= LADDER_STEPS:
        top = cur_ranked[0]
        cur_model, current = (*cur_model, top.effect), top._evaluated
        steps.append({"model": list(cur_model), "added": top.effect, "rms": current.rms,
                      "p_value": top.p_value})
        # Effects that explained nothing significant alone are not retried (saves refits).
        rest = [c.effect for c in cur_ranked[1:] if c.p_value < cand.P_VALUE]
        cur_ranked = _rank(current, cur_model, rest, fitter, track, m, cov, nf.floor) if rest else []
    verdict = "effect_missing" if ranked and ranked[0].significant else "at_noise_floor"
    outliers = ~base.inliers
    return Diagnosis(
        model=tuple(model), n=len(m), n_outliers=int(outliers.sum()), rms=base.rms,
        noise_floor=nf.floor, verdict=verdict, candidates=ranked,
        outlier_spans=outlier_spans(t, outliers), ladder=steps,
        residual_families=families(base.cal, m, cov, base.inliers, base.r, base.x),
        noise={"sigma_axes": [float(v) for v in nf.sigma_axes], "lsb": [float(v) for v in nf.lsb],
               "method": nf.method, "n_used": nf.n_used},
        calibration=base.cal)
