"""Vasconcelos et al. (2011): geometric ellipsoid fit by nonlinear least squares.

Start from the algebraic L2 ellipsoid fit (:func:`streamcal.fitting.ellipsoid.fit_l2_ellipsoid`,
model via Algorithm 1), then minimize (paper Table I)

    Σ_j r_j²,    r_j = ‖T (m_j − b)‖ − 1,

jointly over T upper triangular (6 entries, row-major: t11 t12 t13 t22 t23 t33) and b (3), and
return A = T⁻¹. With v_j = m_j − b, z_j = T v_j, n_j = ‖z_j‖ the Jacobian rows are

    ∂r_j/∂T_ik = z_ji v_jk / n_j   (i ≤ k),        ∂r_j/∂b = −z_jᵀ T / n_j.

The minimization uses MINPACK's Levenberg–Marquardt through ``scipy.optimize.least_squares``
(``method="lm"``); ``ftol`` is the paper's relative function tolerance and ``max_nfev`` bounds
the iterations (each LM iteration evaluates the residuals at least once).
"""
from __future__ import annotations

import numpy as np
import scipy.optimize

from ..calibration import canonical_form
from ..errors import InsufficientDataError
from .ellipsoid import ellipsoid_to_model, fit_l2_ellipsoid
from .reference import check_samples

MIN_SAMPLES = 10
_ROWS, _COLS = np.triu_indices(3)


def fit_vasconcelos(m_n: np.ndarray, *, max_iter: int = 300, rtol: float = 1e-6,
                    init: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``m_n ≈ A x + b`` by Vasconcelos' geometric ellipsoid fit.

    Args:
        m_n: (N,3) normalized samples.
        max_iter: bound on residual evaluations of the LM (paper §III-A: 300 iterations).
        rtol: relative change of the cost at which to stop (paper: 1e-6).
        init: optional starting ``(A, b)``; default the L2 ellipsoid fit of ``m_n``.

    Returns:
        ``(A, b)``: (3,3) upper triangular sensor matrix and (3,) offset, normalized units.
    """
    m = check_samples(m_n, "vasconcelos", MIN_SAMPLES)
    if init is None:
        init = ellipsoid_to_model(*fit_l2_ellipsoid(m))
    K0, _ = canonical_form(init[0])  # ‖T v‖ is blind to rotations, so start upper triangular
    T0 = np.linalg.inv(K0)
    p0 = np.concatenate([T0[_ROWS, _COLS], np.asarray(init[1], dtype=float)])
    result = scipy.optimize.least_squares(
        _residuals, p0, jac=_jacobian, args=(m,), method="lm", ftol=rtol, max_nfev=max_iter)
    T, b = _unpack(result.x)
    if not np.all(np.isfinite(result.x)) or abs(np.prod(np.diag(T))) < 1e-12:
        raise InsufficientDataError("vasconcelos: the fitted ellipsoid is degenerate; the samples "
                                    "do not span three dimensions")
    return np.linalg.inv(T), b


def _unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = np.zeros((3, 3))
    T[_ROWS, _COLS] = p[:6]
    return T, p[6:]


def _residuals(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    T, b = _unpack(p)
    return np.linalg.norm((m - b) @ T.T, axis=1) - 1.0


def _jacobian(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    T, b = _unpack(p)
    v = m - b
    z = v @ T.T
    n = np.maximum(np.linalg.norm(z, axis=1), np.finfo(float).tiny)[:, None]
    return np.hstack([z[:, _ROWS] * v[:, _COLS], -(z @ T)]) / n
