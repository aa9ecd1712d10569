"""Dorveaux et al. (2009): geometric ellipsoid fitting by iterated affine corrections.

The current calibrated samples y_j start as the measurements (A = I, b = 0). Each iteration
(paper Table I)

    1. (L, c) ← argmin Σ_j ‖L y_j + c − y_j / ‖y_j‖‖²    (N×4 linear least squares),
    2. y_j ← L y_j + c,
    3. accumulate the calibration map y = W m + w:  W ← L W,  w ← L w + c,

so the samples are pulled, one affine map at a time, onto the unit sphere. The objective

    F = Σ_j (‖y_j‖ − 1)²

never increases: (L, c) = (I, 0) is a candidate in step 1, whose value is F, and after step 2
each y_j is no farther from the sphere than from the old y_j / ‖y_j‖. Iteration stops when F
changes by less than ``rtol`` relative, or after ``max_iter`` iterations. The sensor model is
the inverse map: A = W⁻¹, b = −W⁻¹ w (equivalently Table I's A ← A L⁻¹, b ← b − A c).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import InsufficientDataError
from .reference import check_samples, converged

MIN_SAMPLES = 4


def fit_dorveaux(m_n: np.ndarray, *, max_iter: int = 300, rtol: float = 1e-6,
                 callback: Callable[[int, float], None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``m_n ≈ A x + b`` by Dorveaux's iteration.

    Args:
        m_n: (N,3) normalized samples.
        max_iter: iteration limit (paper §III-A: 300).
        rtol: relative change of F at which to stop (paper: 1e-6).
        callback: called as ``callback(iteration, F)`` with F after each iteration's update.

    Returns:
        ``(A, b)``: (3,3) general sensor matrix and (3,) offset, normalized units.
    """
    m = check_samples(m_n, "dorveaux", MIN_SAMPLES)
    y = m.copy()
    W, w = np.eye(3), np.zeros(3)
    radius = np.linalg.norm(y, axis=1)
    f = float(np.sum((radius - 1.0) ** 2))
    design = np.ones((m.shape[0], 4))
    for k in range(max_iter):
        design[:, :3] = y
        target = y / np.where(radius > 0, radius, 1.0)[:, None]
        P, *_ = np.linalg.lstsq(design, target, rcond=None)  # (4,3): target ≈ design @ P
        L, c = P[:3].T, P[3]
        y = design @ P
        W, w = L @ W, L @ w + c
        radius = np.linalg.norm(y, axis=1)
        f_prev, f = f, float(np.sum((radius - 1.0) ** 2))
        if callback is not None:
            callback(k, f)
        if converged(f_prev, f, rtol):
            break
    try:
        A = np.linalg.inv(W)
    except np.linalg.LinAlgError:
        raise InsufficientDataError(
            "dorveaux: the calibration map became singular; the samples do not span three "
            "dimensions (rotate the sensor through more orientations)") from None
    return A, -A @ w
