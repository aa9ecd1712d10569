"""Which auxiliary channel a residual follows (issue #10: motors, current, throttle).

``aux_interference`` is fitted over every auxiliary channel at once, and on a vehicle the
channels move together (throttle, the four motor outputs, battery current and voltage sag), so
its per-channel coefficients trade against each other and do not say which channel it is. Here
each channel is scored alone: the multiple correlation r between the signed normal residual
s_j of the base model and the three columns n_j z_j (n_j the surface normal, z_j the channel
centred on its median and scaled by its spread) — the score test of ``aux_interference`` on
that one channel. The channel with the largest r is the one the residual follows most.

Every sample counts, not only the base model's inliers: a motor field of a few µT moves whole
segments (motors off on the ground) beyond the robust width, and those segments are where the
channel shows. So that a few glitches do not decide it, s is clipped at the 99th percentile
of |s|.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ...model._common import aux_names


#: s is clipped at this percentile of |s| before scoring.
CLIP_PERCENTILE = 99.0


def channel_scores(s: np.ndarray, normal: np.ndarray,
                   cov: Mapping[str, np.ndarray]) -> dict[str, float]:
    """``{channel: r}`` (0..1), largest first, for every auxiliary channel in ``cov`` that
    varies. ``s`` (N,) signed normal residual (sensor unit), ``normal`` (N,3)."""
    s = np.asarray(s, float)
    inl = np.isfinite(s) & np.all(np.isfinite(normal), axis=1)
    if not inl.any():
        return {}
    lim = float(np.percentile(np.abs(s[inl]), CLIP_PERCENTILE))
    y = np.clip(s[inl], -lim, lim)
    sst = float(np.sum((y - y.mean()) ** 2)) if len(y) else 0.0
    out = {}
    for name in aux_names(cov):
        c = np.asarray(cov[name], float)[inl]
        if len(c) < 10 or not np.all(np.isfinite(c)):
            continue
        spread = float(np.std(c))
        if spread <= 0 or sst <= 0:
            continue
        z = (c - np.median(c)) / spread
        A = np.column_stack([np.ones(len(y)), np.asarray(normal, float)[inl] * z[:, None]])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        out[name] = float(np.sqrt(max(0.0, 1 - np.sum((y - A @ coef) ** 2) / sst)))
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))
