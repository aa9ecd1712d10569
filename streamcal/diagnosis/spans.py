"""Outlier spans: time intervals where outliers cluster."""
from __future__ import annotations

import numpy as np

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
