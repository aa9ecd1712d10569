"""Fitter used by the diagnosis tests: ``streamcal.fitting.fit`` when it is there, else the stage-2
LM (``streamcal.fitting.lm.refine``) started from a sphere on normalized data."""
import numpy as np

from streamcal.calibration import Calibration
from streamcal.model import build_effects


def fitter(track, model, initial=None):
    try:
        from streamcal.fitting import fit
    except ImportError:
        fit = None
    if fit is not None:
        return fit(track, model=tuple(model), kernel="cauchy", initial=initial)
    from streamcal.fitting.kernels import Cauchy
    from streamcal.fitting.lm import refine
    from streamcal.fitting.normalize import normalize

    m = track.mag
    cov = track.covariates_at_mag()
    mn, center, scale = normalize(m)
    effects = build_effects(model, cov)
    x = mn / np.linalg.norm(mn, axis=1, keepdims=True)
    K0 = np.eye(3) * np.median(np.linalg.norm(mn, axis=1))
    res = refine(mn, K0, np.zeros(3), x, kernel=Cauchy(0.05), effects=effects, covariates=cov)
    inl = res.weights > 0.25
    return Calibration(K=res.K * scale, b=res.b * scale + center, model=tuple(model),
                       effects={e.name: e.to_physical(th, scale) for e, th in zip(effects, res.thetas)},
                       n=len(m), n_outliers=int((~inl).sum()), inliers=inl, weights=res.weights)
