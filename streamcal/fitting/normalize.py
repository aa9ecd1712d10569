"""Data normalization (paper §II-B): subtract the median, divide by the standard deviation."""
from __future__ import annotations

import numpy as np

from .order_stats import column_medians


def normalize(m: np.ndarray):
    """Return ``(m_n, center, scale)`` with ``m_n = (m − center) / scale``.

    ``m`` (N,3) in the sensor unit; ``center`` (3,) the per-axis median; ``scale`` a single
    float, the standard deviation of all centred coordinates (one scale for all axes keeps the
    model's geometry, so K_n is K / scale).
    """
    m = np.asarray(m, dtype=float)
    center = column_medians(m)
    centred = m - center
    scale = float(np.sqrt(np.mean(centred ** 2)))
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    centred /= scale
    return centred, center, scale


def denormalize_model(K_n: np.ndarray, b_n: np.ndarray, center: np.ndarray, scale: float):
    """Model in the sensor unit from the model fitted to normalized data: K = s K_n, b = s b_n + c."""
    return scale * np.asarray(K_n), scale * np.asarray(b_n) + center
