"""Quantiles and medians of small 1-D samples by one partial sort, the same numbers as
``np.quantile`` (method ``linear``) and ``np.median``.

At N ≈ 1000 numpy's general versions spend most of their ~20–60 µs in argument handling
(axes, NaN checks, moving axes); the robust fit calls them a dozen times per fit. Both
functions below partition once and interpolate exactly as numpy does (``_lerp``), so results
are bit-for-bit equal (signed zeros included); anything but a finite 1-D float sample goes to numpy itself.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def quantiles(a: np.ndarray, qs: Sequence[float]) -> list[float]:
    """``[np.quantile(a, q) for q in qs]`` for a 1-D array ``a`` (N,), as Python floats."""
    a = np.asarray(a)
    n = a.shape[0] if a.ndim == 1 else 0
    if n == 0 or a.dtype != np.float64 or not np.isfinite(a).all():
        return [float(v) for v in np.atleast_1d(np.quantile(a, qs))]
    spots = []
    for q in qs:
        virtual = (n - 1) * float(q)
        lo = min(max(int(math.floor(virtual)), 0), n - 1)
        spots.append((virtual, lo, min(lo + 1, n - 1)))
    # numpy's own partition points (first, last and the neighbours), so that equal values
    # (0.0 and -0.0) land in the same places
    part = np.partition(a, sorted({0, n - 1} | {i for _, lo, hi in spots for i in (lo, hi)}))
    out = []
    for virtual, lo, hi in spots:
        below, above, t = float(part[lo]), float(part[hi]), virtual - lo
        diff = above - below
        out.append(above - diff * (1 - t) if t >= 0.5 else below + diff * t)
    return out


def quantile(a: np.ndarray, q: float) -> float:
    """``float(np.quantile(a, q))`` for a 1-D array ``a`` (N,)."""
    return quantiles(a, (q,))[0]


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` for a 1-D array ``a`` (N,)."""
    a = np.asarray(a)
    n = a.shape[0] if a.ndim == 1 else 0
    if n == 0 or a.dtype != np.float64 or not np.isfinite(a).all():
        return float(np.median(a))
    half = n // 2
    # numpy averages the middle value(s) as a sum from 0.0: a median of -0.0s is +0.0
    if n % 2:
        return 0.0 + float(np.partition(a, sorted({half, n - 1}))[half])
    part = np.partition(a, sorted({half - 1, half, n - 1}))
    return (0.0 + float(part[half - 1]) + float(part[half])) / 2.0


def sorted_median(ordered: np.ndarray, k: int) -> float:
    """``median(ordered[:k])`` for an ascending 1-D array (k ≥ 1): no partition needed, so a
    caller that sorts once can take the median of any prefix."""
    half = k // 2
    if k % 2:
        return 0.0 + float(ordered[half])
    return (0.0 + float(ordered[half - 1]) + float(ordered[half])) / 2.0


def column_medians(m: np.ndarray) -> np.ndarray:
    """``np.median(m, axis=0)`` for an (N,k) array, column by column (k,)."""
    m = np.asarray(m)
    if m.ndim != 2 or m.dtype != np.float64 or m.shape[0] == 0:
        return np.median(m, axis=0)
    if not np.isfinite(m).all():
        return np.array([median(np.ascontiguousarray(m[:, j])) for j in range(m.shape[1])])
    # every column at once: one partition of mᵀ along its rows, the points and arithmetic of
    # :func:`median` (a third of the cost of three separate calls at N = 1000)
    n, half = m.shape[0], m.shape[0] // 2
    if n % 2:
        return 0.0 + np.partition(m.T, sorted({half, n - 1}), axis=1)[:, half]
    part = np.partition(m.T, sorted({half - 1, half, n - 1}), axis=1)
    return (0.0 + part[:, half - 1] + part[:, half]) / 2.0
