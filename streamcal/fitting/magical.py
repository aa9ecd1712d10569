"""MAG.I.C.AL. (Papafotis & Sotiriadis 2019): minimize the sensor estimation error by alternation.

Objective (paper Table I), over the model (A, b) and unit directions x_j::

    F(A, b, {x_j}) = Σ_j ‖A x_j + b − m_j‖²

Start from x_j = m_j / ‖m_j‖ (that is, A = I, b = 0) and repeat

    1. (A, b) ← argmin F given {x_j}: one linear least-squares problem,
                 [x_jᵀ 1] [Aᵀ; bᵀ] = m_jᵀ  for all j   (N×4 design, 3 right-hand sides);
    2. x_j ← A⁻¹ (m_j − b): the unconstrained minimizer of F over x_j;
    3. x_j ← x_j / ‖x_j‖,

until F after step 1 changes by less than ``rtol`` relative, or ``max_iter`` iterations.
Steps 2–3 are a radial projection, not the exact minimizer on the sphere, so F is not
guaranteed to decrease at every iteration (it does in practice once near the solution).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import InsufficientDataError
from .reference import check_samples, converged

MIN_SAMPLES = 4


def fit_magical(m_n: np.ndarray, *, max_iter: int = 300, rtol: float = 1e-6,
                callback: Callable[[int, float], None] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``m_n ≈ A x + b`` by MAG.I.C.AL. alternation.

    Args:
        m_n: (N,3) normalized samples.
        max_iter: iteration limit (paper §III-A: 300).
        rtol: relative change of F at which to stop (paper: 1e-6).
        callback: called as ``callback(iteration, F)`` after each least-squares step.

    Returns:
        ``(A, b)``: (3,3) general sensor matrix and (3,) offset, normalized units.
    """
    m = check_samples(m_n, "magical", MIN_SAMPLES)
    norms = np.linalg.norm(m, axis=1, keepdims=True)
    x = m / np.where(norms > 0, norms, 1.0)
    design = np.ones((m.shape[0], 4))
    f_prev = np.inf
    for k in range(max_iter):
        design[:, :3] = x
        P, *_ = np.linalg.lstsq(design, m, rcond=None)  # (4,3): m ≈ design @ P
        A, b = P[:3].T, P[3]
        f = float(np.sum((design @ P - m) ** 2))
        if callback is not None:
            callback(k, f)
        if k > 0 and converged(f_prev, f, rtol):
            break
        f_prev = f
        try:
            u = np.linalg.solve(A, (m - b).T).T
        except np.linalg.LinAlgError:
            raise InsufficientDataError(
                "magical: the fitted sensor matrix is singular; the samples do not span "
                "three dimensions (rotate the sensor through more orientations)") from None
        x = u / np.linalg.norm(u, axis=1, keepdims=True)
    return A, b
