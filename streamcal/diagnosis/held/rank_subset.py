"""The samples the candidate refits of a long recording use (issue #10 speed target).

Ranking candidate effects refits the model once per candidate; on a 20-minute flight that is
most of the time a diagnosis takes. The refits use a subsample that keeps every occupied cell
of (direction seen × stretch of time): the directions are binned into :data:`AZIMUTHS` ×
:data:`BANDS` equal-area cells (azimuth × equal z-width bands of (m − b)/‖m − b‖) and the time
span into :data:`TIME_BINS` equal stretches; each occupied (cell, stretch) group keeps samples
evenly spaced in time, in proportion to its size and at least one. So no direction and no part
of the flight (the hot end, the full-throttle climb) drops out, and a channel's range is kept.
"""
from __future__ import annotations

import numpy as np

#: Candidate refits use a subsample of about this many samples when the recording has more
#: than twice as many (below that the saving would not pay for the extra base refit).
RANK_MAX = 1500
AZIMUTHS, BANDS, TIME_BINS = 12, 6, 24


def rank_subset(m: np.ndarray, b: np.ndarray, t: np.ndarray,
                n_max: int = RANK_MAX) -> np.ndarray | None:
    """Sorted indices (K,) of the subsample, or None when ``len(m) <= 2 n_max`` (use all).

    ``m`` (N,3) readings and ``b`` (3,) the offset the directions are seen from (sensor unit),
    ``t`` (N,) time (s). K is about ``n_max``, more when there are more occupied groups."""
    n = len(m)
    if n <= 2 * n_max:
        return None
    d = np.asarray(m, float) - np.asarray(b, float)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    az = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * AZIMUTHS)
    band = np.floor((np.clip(d[:, 2], -1, 1) + 1) / 2 * BANDS)
    t = np.asarray(t, float)
    span = float(np.ptp(t)) or 1.0
    tb = np.floor((t - t.min()) / span * TIME_BINS)
    key = (np.clip(az, 0, AZIMUTHS - 1) * BANDS + np.clip(band, 0, BANDS - 1)) * (TIME_BINS + 1) \
        + np.clip(tb, 0, TIME_BINS)
    order = np.lexsort((t, key))
    k_sorted = key[order]
    start = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
    size = np.diff(np.r_[start, n])
    group = np.repeat(np.arange(len(start)), size)
    rank = np.arange(n) - start[group]
    quota = np.maximum(1, np.round(size * n_max / n)).astype(int)[group]
    size_g = size[group]
    # keep rank r when floor(r·q/size) steps up: q samples evenly spaced through the group
    keep = (rank == 0) | (np.floor(rank * quota / size_g) != np.floor((rank - 1) * quota / size_g))
    return np.sort(order[keep])
