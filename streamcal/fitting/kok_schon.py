"""Kok & Schön (2016): the algebraic L2 ellipsoid fit as a semidefinite program.

Each sample gives the algebraic residual (paper eq. 5)

    g_j = m_jᵀ C m_j + 2 dᵀ m_j + e = M_j θ,
    M_j = [x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z, 1],  θ = [C11 C22 C33 C12 C13 C23 d1 d2 d3 e],

and the fit is

    minimize ‖M θ‖²   subject to   C ⪰ 0,  trace(C) = 1,

(M as :func:`streamcal.fitting.ellipsoid.design_matrix`), whose global minimum a conic solver finds
(Clarabel here; SeDuMi in the papers). With M = Q R (thin QR), ‖M θ‖ = ‖R θ‖ for the 10×10
factor R, so the program has the same size for every N; it is built once with R as a
``cvxpy.Parameter`` and re-solved. The model follows from
Algorithm 1 (:func:`streamcal.fitting.ellipsoid.ellipsoid_to_model`).
"""
from __future__ import annotations

import threading

import numpy as np

from ..errors import InsufficientDataError
from .ellipsoid import design_matrix, ellipsoid_to_model
from .reference import check_samples

MIN_SAMPLES = 10
_ACCEPTED = ("optimal", "optimal_inaccurate")
_lock = threading.Lock()
_problem = None  # (cvxpy.Problem, R parameter, C, d, e variables), built on first use


def solve_kok_schon_sdp(m_n: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Solve the SDP for normalized samples ``m_n`` (N,3).

    Returns:
        ``(C (3,3) symmetric PSD with unit trace, d (3,), e, objective ‖M θ‖²)``.
    """
    import cvxpy as cp

    m = check_samples(m_n, "kok_schon", MIN_SAMPLES)
    R = np.linalg.qr(design_matrix(m), mode="r")
    with _lock:
        problem, R_param, C, d, e = _get_problem()
        R_param.value = R
        try:
            problem.solve(solver=cp.CLARABEL)
        except cp.error.SolverError as exc:
            raise InsufficientDataError(f"kok_schon: the ellipsoid SDP failed ({exc})") from None
        if problem.status not in _ACCEPTED:
            raise InsufficientDataError(f"kok_schon: the ellipsoid SDP ended with status "
                                        f"'{problem.status}'")
        Cv = np.array(C.value)
        return (Cv + Cv.T) / 2, np.array(d.value), float(e.value), float(problem.value)


def fit_kok_schon(m_n: np.ndarray, *, max_iter: int = 300, rtol: float = 1e-6
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``m_n ≈ K x + b`` by the Kok–Schön SDP and Algorithm 1.

    ``max_iter`` and ``rtol`` are accepted for a uniform signature; the conic solver uses its
    own stopping rules (the method has no refinement stage).

    Returns:
        ``(K, b)``: (3,3) upper triangular sensor matrix and (3,) offset, normalized units.
    """
    C, d, e, _ = solve_kok_schon_sdp(m_n)
    return ellipsoid_to_model(C, d, e)


def _get_problem():
    global _problem
    if _problem is None:
        import cvxpy as cp

        R = cp.Parameter((10, 10), name="R")
        C = cp.Variable((3, 3), symmetric=True, name="C")
        d = cp.Variable(3, name="d")
        e = cp.Variable(name="e")
        theta = cp.hstack([C[0, 0], C[1, 1], C[2, 2], C[0, 1], C[0, 2], C[1, 2], d, e])
        problem = cp.Problem(cp.Minimize(cp.sum_squares(R @ theta)),
                             [C >> 0, cp.trace(C) == 1])
        _problem = (problem, R, C, d, e)
    return _problem
