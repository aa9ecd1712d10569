"""Stage 1 (paper §II-C, Algorithm 1): algebraic ellipsoid fits and the model they give.

The ellipsoid ``yᵀC y + 2dᵀy + e = 0`` (eq. 3) is linear in v = [C11 C22 C33 C12 C13 C23 d1 d2 d3 e],
so the algebraic residuals of all samples are ``g = Φ v`` with the design matrix Φ (N,10).

- L2 (Kok & Schön's SVD form): minimize ‖Φv‖₂ subject to ‖v‖ = 1.
- L1 (Calafiore, eq. 6): minimize ‖Φv‖₁ subject to trace(C) = 1 and C ⪰ 0 — a convex program.
  Two equivalent solvers: :class:`L1EllipsoidProblem` builds it once in cvxpy with a Parameter
  for Φ (re-solved per call, Clarabel backend), and :func:`fit_l1_ellipsoid` hands its dual
  straight to Clarabel, skipping cvxpy's canonicalization (~10× less overhead).
  ``tests/test_ellipsoid.py`` checks that both reach the same optimum.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.linalg.lapack import dsyevr

from ..errors import InsufficientDataError
from .order_stats import column_medians

SQRT2 = np.sqrt(2.0)


def design_matrix(m: np.ndarray) -> np.ndarray:
    """Φ (N,10) such that Φ v = mᵀCm + 2dᵀm + e for every sample (m (N,3), normalized)."""
    return np.ascontiguousarray(_design_rows(m).T)


def _design_rows(m: np.ndarray) -> np.ndarray:
    """Φᵀ (10,N) built row by contiguous row (half the cost of an (N,10) column stack at
    N = 1000): x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z, 1."""
    mt = np.ascontiguousarray(np.asarray(m, dtype=float).T)
    x, y, z = mt
    pt = np.empty((10, mt.shape[1]))
    np.multiply(mt, mt, out=pt[0:3])
    np.multiply(x, y, out=pt[3])
    np.multiply(x, z, out=pt[4])
    np.multiply(y, z, out=pt[5])
    pt[3:6] *= 2
    np.multiply(mt, 2, out=pt[6:9])
    pt[9] = 1.0
    return pt


def unpack(v: np.ndarray):
    """(C (3,3), d (3,), e) from the 10-vector v."""
    c11, c22, c33, c12, c13, c23, d1, d2, d3, e = v
    C = np.array([[c11, c12, c13], [c12, c22, c23], [c13, c23, c33]])
    return C, np.array([d1, d2, d3]), float(e)


def _scatter(m: np.ndarray) -> np.ndarray:
    """Φᵀ Φ (10,10) of :func:`design_matrix`."""
    pt = _design_rows(m)
    return pt @ pt.T


def fit_l2_ellipsoid(m: np.ndarray):
    """Algebraic least-squares ellipsoid: the right singular vector of Φ for its smallest
    singular value; returns (C, d, e) scaled to trace(C) = 1."""
    # Φᵀ Φ (10×10) has the same right singular vectors; cheaper than an SVD of (N,10). Only the
    # smallest eigenpair, from LAPACK's dsyevr directly (half the time of np.linalg.eigh here).
    scatter = _scatter(m)
    if not np.isfinite(scatter).all():  # dsyevr would return a zero vector without an error
        raise InsufficientDataError("the algebraic ellipsoid fit needs finite samples")
    _, V, _, _, info = dsyevr(scatter, range="I", il=1, iu=1)
    if info:
        raise InsufficientDataError(f"the algebraic ellipsoid fit failed (LAPACK dsyevr info {info})")
    v = V[:, 0]
    C, d, e = unpack(v)
    tr = np.trace(C)
    if tr == 0:
        raise InsufficientDataError("the algebraic ellipsoid fit is degenerate (trace of C is 0)")
    return unpack(v / tr)


#: svec(C) = S v for Clarabel's PSD cone (upper triangle by columns, off-diagonals × √2):
#: row k of S has the single entry SVEC_VAL[k] in column SVEC_COL[k] of v.
SVEC_COL = np.array([0, 3, 1, 4, 5, 2])
SVEC_VAL = np.array([1.0, SQRT2, 1.0, SQRT2, SQRT2, 1.0])


def fit_l1_ellipsoid(m: np.ndarray, *, tol: float = 1e-8):
    """Calafiore's L1 ellipsoid fit (eq. 6) solved directly with Clarabel; returns (C, d, e).

    Clarabel is handed the Lagrange dual of eq. 6, which is smaller to factor than the primal
    (10 dense rows instead of 10 dense columns against 2N inequality rows; ~2× faster at
    N = 300 for the same optimum):

        maximize μ  over λ (N), μ, Z ⪰ 0,   subject to  Φᵀλ = μ t + Sᵀ svec(Z),  −1 ≤ λ ≤ 1,

    with t the trace row of v and S the svec map. Clarabel's form: variables [λ, μ, svec(Z)],
    minimize −μ, rows = the 10 equalities (zero cone), λ ≤ 1 and −λ ≤ 1 (nonnegative cone, 2N),
    −svec(Z) ≤ 0 (PSD cone). The primal optimum v is minus the multipliers of the 10 equalities
    (and the objective the same by strong duality: both problems are strictly feasible).
    Iterative refinement of the KKT solves is skipped (it costs a third of the time and moves
    v by < 1e-10 here); a solve that does not report success is retried with it.
    """
    import clarabel

    phi = design_matrix(m)
    n = phi.shape[0]
    # A in CSC, column by column: λ_j → Φ[j] in rows 0–9, +1 in row 10+j, −1 in row 10+N+j;
    # μ → −1 in rows 0–2 (−t); svec(Z)_k → −SVEC_VAL[k] in row SVEC_COL[k], −1 in row 10+2N+k.
    rows = np.empty(12 * n + 15, dtype=np.int64)
    data = np.empty(12 * n + 15)
    r_lam, d_lam = rows[:12 * n].reshape(n, 12), data[:12 * n].reshape(n, 12)
    r_lam[:, :10] = np.arange(10)
    r_lam[:, 10] = 10 + np.arange(n)
    r_lam[:, 11] = 10 + n + np.arange(n)
    d_lam[:, :10] = phi
    d_lam[:, 10] = 1.0
    d_lam[:, 11] = -1.0
    rows[12 * n:12 * n + 3] = (0, 1, 2)
    data[12 * n:12 * n + 3] = -1.0
    r_z, d_z = rows[12 * n + 3:].reshape(6, 2), data[12 * n + 3:].reshape(6, 2)
    r_z[:, 0] = SVEC_COL
    r_z[:, 1] = 10 + 2 * n + np.arange(6)
    d_z[:, 0] = -SVEC_VAL
    d_z[:, 1] = -1.0
    indptr = np.r_[np.arange(0, 12 * n + 1, 12), 12 * n + 3 + 2 * np.arange(7)]
    A = sp.csc_matrix((data, rows, indptr), shape=(16 + 2 * n, n + 7))
    b = np.r_[np.zeros(10), np.ones(2 * n), np.zeros(6)]
    q = np.zeros(n + 7)
    q[n] = -1.0
    P = sp.csc_matrix((n + 7, n + 7))
    cones = [clarabel.ZeroConeT(10), clarabel.NonnegativeConeT(2 * n), clarabel.PSDTriangleConeT(3)]
    status = None
    for refine_kkt in (False, True):
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = tol
        settings.iterative_refinement_enable = refine_kkt
        solution = clarabel.DefaultSolver(P, q, A, b, cones, settings).solve()
        status = str(solution.status)
        if status == "Solved":
            break
    if "Solved" not in status:
        raise InsufficientDataError(f"the L1 ellipsoid program did not solve (Clarabel: {status})")
    return unpack(-np.asarray(solution.z[:10]))


class L1EllipsoidProblem:
    """The same L1 program written in cvxpy once (Φ a Parameter), solved by Clarabel.

    Build once per sample count and call repeatedly: cvxpy caches the canonicalization.
    """

    def __init__(self, n: int):
        import cvxpy as cp

        self.n = n
        self.phi = cp.Parameter((n, 10), name="phi")
        self.C = cp.Variable((3, 3), PSD=True, name="C")
        self.d = cp.Variable(3, name="d")
        self.e = cp.Variable(name="e")
        C = self.C
        v = cp.hstack([C[0, 0], C[1, 1], C[2, 2], C[0, 1], C[0, 2], C[1, 2], self.d, cp.reshape(self.e, (1,), order="C")])
        self.problem = cp.Problem(cp.Minimize(cp.norm1(self.phi @ v)), [cp.trace(C) == 1])

    def solve(self, m: np.ndarray):
        import cvxpy as cp

        phi = design_matrix(m)
        if phi.shape[0] != self.n:
            raise ValueError(f"problem built for {self.n} samples, got {phi.shape[0]}")
        self.phi.value = phi
        self.problem.solve(solver=cp.CLARABEL)
        if self.problem.status not in ("optimal", "optimal_inaccurate"):
            raise InsufficientDataError(f"the L1 ellipsoid program did not solve (cvxpy: {self.problem.status})")
        C = np.asarray(self.C.value)
        return 0.5 * (C + C.T), np.asarray(self.d.value), float(self.e.value)


def ellipsoid_to_model(C: np.ndarray, d: np.ndarray, e: float):
    """Algorithm 1, steps 2–4: b = −C⁻¹d, μ = −bᵀd − e, K = √μ · chol(C)⁻¹ (upper triangular).

    Raises :class:`InsufficientDataError` when (C, d, e) is not a real ellipsoid.
    """
    # 3×3 by hand, in floats: numpy's cholesky, solve and inverse cost ~10 µs each in call
    # overhead, ten times their arithmetic
    (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = np.asarray(C, dtype=float).tolist()
    d0, d1, d2 = np.asarray(d, dtype=float).tolist()
    # C = L Lᵀ (Cholesky of the symmetric part; a pivot ≤ 0 or NaN: not positive definite)
    l00 = math.sqrt(c00) if c00 > 0 else math.nan
    l10, l20 = 0.5 * (c01 + c10) / l00, 0.5 * (c02 + c20) / l00
    p11 = c11 - l10 * l10
    l11 = math.sqrt(p11) if p11 > 0 else math.nan
    l21 = (0.5 * (c12 + c21) - l20 * l10) / l11
    p22 = c22 - l20 * l20 - l21 * l21
    l22 = math.sqrt(p22) if p22 > 0 else math.nan
    if not (l00 > 0 and l11 > 0 and l22 > 0 and math.isfinite(l00 * l11 * l22)):
        raise InsufficientDataError(
            "the fitted quadric is not an ellipsoid (C is not positive definite): the data do "
            "not outline an ellipsoid — rotate the sensor through more orientations")
    # L⁻¹ (lower triangular), then b = −C⁻¹d = −L⁻ᵀ(L⁻¹d) and K = √μ L⁻ᵀ (upper triangular)
    i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    i10 = -l10 * i00 * i11
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22
    y0, y1, y2 = i00 * d0, i10 * d0 + i11 * d1, i20 * d0 + i21 * d1 + i22 * d2
    b = np.array([-(i00 * y0 + i10 * y1 + i20 * y2), -(i11 * y1 + i21 * y2), -(i22 * y2)])
    mu = -(b[0] * d0 + b[1] * d1 + b[2] * d2) - float(e)
    if not math.isfinite(mu) or mu <= 0:
        raise InsufficientDataError("the fitted quadric is empty or imaginary (μ ≤ 0)")
    root = math.sqrt(mu)
    K = np.array([[i00, i10, i20], [0.0, i11, i21], [0.0, 0.0, i22]])
    K *= root
    return K, b


def directions_from_model(K: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Algorithm 1, steps 5–7: x_j = K⁻¹(m_j − b) / ‖·‖, shape (N,3)."""
    x = (np.asarray(m) - b) @ np.linalg.inv(K).T     # one 3×3 inverse: ~4× a batched solve
    norm = np.sqrt(np.einsum("ij,ij->i", x, x))[:, None]
    return x / np.where(norm > 0, norm, 1.0)


def directions_and_residuals(K: np.ndarray, b: np.ndarray, m: np.ndarray):
    """(x, r, relative) at the model (K, b) for samples m (N,3) from one solve: the directions
    of :func:`directions_from_model` (N,3), the residual norms ‖K x_j + b − m_j‖ (N,) and the
    radial errors |‖K⁻¹(m_j − b)‖ − 1| (N,) (``robust_start.radial_error``).

    With u = K⁻¹(m − b), K x + b − m = (m − b)(1/‖u‖ − 1): the residual needs no product."""
    d = np.asarray(m) - b
    u = np.linalg.inv(K) @ d.T                        # (3, N)
    norm = np.sqrt(np.einsum("ij,ij->j", u, u))
    safe = np.where(norm > 0, norm, 1.0)              # a sample at b: x = 0, r = 0
    x = (u / safe).T
    r = np.sqrt(np.einsum("ij,ij->i", d, d)) * np.abs(1.0 - 1.0 / safe)
    return x, r, np.abs(norm - 1.0)


def spread_subset(m: np.ndarray, n_max: int, seed: int = 0) -> np.ndarray:
    """Indices of at most ``n_max`` samples spread evenly over the directions seen from the
    median: round-robin over 12×6 equal-area cells (12 azimuths × 6 bands of equal z-width),
    so a long dwell in one orientation does not crowd out the rest."""
    m = np.asarray(m, dtype=float)
    n = m.shape[0]
    if n <= n_max:
        return np.arange(n)
    v = m - column_medians(m)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    az = np.minimum(np.maximum(np.floor((np.arctan2(v[:, 1], v[:, 0]) + np.pi) / (2 * np.pi) * 12), 0), 11)
    band = np.minimum(np.maximum(np.floor((v[:, 2] + 1.0) / 2.0 * 6), 0), 5)
    cell = (band * 12 + az).astype(int)
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    cell_sorted = cell[order]
    by_cell = np.argsort(cell_sorted, kind="stable")
    # rank of each sample inside its cell (in the random order)
    sorted_cells = cell_sorted[by_cell]
    starts = np.concatenate(([0], np.flatnonzero(np.diff(sorted_cells)) + 1))
    counts = np.diff(np.concatenate((starts, [n])))
    rank_sorted = np.arange(n) - np.repeat(starts, counts)
    rank = np.empty(n, dtype=int)
    rank[by_cell] = rank_sorted
    # by rank, ties by a random key: np.lexsort((key, rank)) as two stable argsorts (faster)
    by_key = np.argsort(rng.random(n), kind="stable")
    pick = by_key[np.argsort(rank[by_key], kind="stable")[:n_max]]
    return np.sort(order[pick])
