"""The one outlier rule of every fit and diagnosis, and the spans where outliers cluster.

A sample is an outlier of a fitted model when its residual norm lies beyond
:data:`~streamcal.constants.OUTLIER_WIDTHS` kernel widths of that model's fit, or on the ramp of a
disturbance around such outliers (:func:`widen_outliers`). ``streamcal fit`` reports its rms over
the complement, and a diagnosis counts the same way, model by model: a sample that an added
effect explains is an inlier of the model with it."""
from __future__ import annotations

import numpy as np

from ..constants import HALF_NORMAL_MEDIAN, OUTLIER_WIDTHS

#: Outliers closer than this (s) belong to the same span.
MAX_GAP_S = 1.0
#: A span needs at least this many outliers (isolated points are not reported).
MIN_COUNT = 2


def outlier_spans(t: np.ndarray, outlier: np.ndarray, max_gap: float = MAX_GAP_S,
                  min_count: int = MIN_COUNT) -> list[list[float]]:
    """``[[t_start, t_end], …]`` (s) over the times ``t`` (N,) of the ``outlier`` (N,) bool mask,
    merging outliers less than ``max_gap`` apart and dropping clusters of fewer than
    ``min_count`` samples."""
    ts = np.sort(np.asarray(t, dtype=float)[np.asarray(outlier, bool)])
    if ts.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(ts) >= max_gap)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [ts.size - 1]])
    keep = (ends - starts + 1) >= min_count
    return [[float(ts[s]), float(ts[e])] for s, e in zip(starts[keep], ends[keep])]


#: A sample's residual counts as raised above this many times the inliers' median norm (the
#: running median over :data:`RAMP_WINDOW_S`; for noise alone that median stays near 1×).
RAMP_LEVEL = 1.5
#: Window (s) of the running median that follows a disturbance's ramp.
RAMP_WINDOW_S = 0.2


def widen_outliers(t: np.ndarray, norm: np.ndarray, outlier: np.ndarray,
                   max_gap: float = MAX_GAP_S, min_count: int = MIN_COUNT) -> np.ndarray:
    """The ``outlier`` (N,) mask widened over the ramps of each disturbance.

    A disturbance (a magnet carried past) rises and falls smoothly: the fit's rule marks its
    peak but leaves the ramps, whose residual is raised yet below the cut, among the inliers,
    inflating the rms. Around each cluster of outliers (as :func:`outlier_spans`, times ``t``
    (N,) s in order), the samples whose running median of the residual norm ``norm`` (N,)
    stays above :data:`RAMP_LEVEL` × the inliers' median norm, continuously from the cluster
    and at most the cluster's own duration (or ``max_gap``) from it, become outliers too.
    A sample whose neighbourhood looks like noise is never added."""
    from scipy.ndimage import median_filter

    t = np.asarray(t, dtype=float)
    norm = np.asarray(norm, dtype=float)
    out = np.asarray(outlier, bool).copy()
    n = len(t)
    if n < 3 or not out.any() or out.all() or np.any(np.diff(t) < 0):
        return out
    dt = float(np.median(np.diff(t)))
    w = max(3, int(round(RAMP_WINDOW_S / dt)) if dt > 0 else 3) | 1
    level = RAMP_LEVEL * float(np.median(norm[~out]))
    raised = median_filter(np.where(np.isfinite(norm), norm, np.inf), size=w,
                           mode="nearest") > level
    for a, b in outlier_spans(t, out, max_gap, min_count):
        reach = max(b - a, max_gap)
        i0 = int(np.searchsorted(t, a, side="left"))
        i1 = int(np.searchsorted(t, b, side="right")) - 1
        lo = int(np.searchsorted(t, a - reach, side="left"))
        hi = int(np.searchsorted(t, b + reach, side="right")) - 1
        # extend left from i0 while raised, right from i1 while raised
        left = raised[lo:i0][::-1]
        k = int(np.argmin(left)) if left.size and not left.all() else left.size
        right = raised[i1 + 1:hi + 1]
        j = int(np.argmin(right)) if right.size and not right.all() else right.size
        out[i0 - k:i1 + 1 + j] = True
    return out


#: Without a kernel width from the fit, a sample is an outlier beyond this many noise σ.
OUTLIER_SIGMAS = 5.0


def outlier_mask(norm: np.ndarray, width: float | None, t: np.ndarray | None = None,
                 floor: float = float("nan")) -> np.ndarray:
    """(N,) bool: outliers of a model whose residual norms are ``norm`` (N,) under a kernel of
    ``width`` (sensor unit): beyond :data:`OUTLIER_WIDTHS` widths — without a width (a
    reference method's fit), beyond :data:`OUTLIER_SIGMAS` × the noise ``floor`` (else the
    norms' robust σ) —, widened over disturbance ramps when the sample times ``t`` (N,) s are
    known."""
    norm = np.asarray(norm, dtype=float)
    if width:
        limit = OUTLIER_WIDTHS * float(width)
    else:
        sigma = floor if np.isfinite(floor) else float(np.median(norm)) / HALF_NORMAL_MEDIAN
        limit = OUTLIER_SIGMAS * sigma
    out = ~(norm <= limit)
    return widen_outliers(t, norm, out) if t is not None else out


def residual_width(norm: np.ndarray, kernel: str = "cauchy") -> float:
    """The kernel width (sensor unit) a fit takes from residual norms ``norm`` (N,): the
    kernel's 95 %-efficiency multiple of σ̂, the robust scale a fit takes of them
    (:func:`streamcal.fitting.autocal.fit_sigma`)."""
    from .autocal import fit_sigma
    from .kernels import EFFICIENCY_TAU

    norm = np.asarray(norm, dtype=float)
    norm = norm[np.isfinite(norm)]
    if not norm.size:
        return float("nan")
    return float(EFFICIENCY_TAU[kernel] * fit_sigma(norm))


def widened_inliers(inliers: np.ndarray, norm: np.ndarray, t: np.ndarray | None) -> np.ndarray:
    """A fit's own (N,) inlier mask with the ramps of each disturbance removed too (the rule of
    :func:`outlier_mask` for a fit that already cut at its widths)."""
    inliers = np.asarray(inliers, bool)
    return inliers if t is None else ~widen_outliers(t, norm, ~inliers)
