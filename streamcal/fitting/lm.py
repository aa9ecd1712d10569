"""Stage 2 (paper §II-D, Algorithm 2): robust Levenberg–Marquardt over the model and the
per-sample field directions on the unit sphere.

Residual of sample j (eq. 7, extended by the effect terms of ``streamcal.model.effect``):

    r_j = u_j + b + Σ_e f_e(θ_e, u_j, c_j) − m_j,      u_j = K x_j,  ‖x_j‖ = 1.

Global parameters p = [k (6, or 3 for a diagonal K, or 1 for K = kI), b (3), θ_1, θ_2, …].
Each iteration (all vectorized over samples; no per-sample Python loop):

1. ρ, ρ′, ρ″ of s_j = ‖r_j‖² from the kernel; Triggs-corrected r̃_j, J̃_j (eq. 22–24).
2. Tangent projection of the direction Jacobian, J̃_{x_j} ← J̃_{x_j}(I − x_j x_jᵀ) (eq. 27).
3. Gauss–Newton blocks (eq. 25–26, 30), damped by λ:

       ┌ H̃_pp   H_px1 … H_pxN ┐ ┌Δp ┐     ┌ g_p ┐
       │ H_px1ᵀ  H̃_x1         │ │Δx1│ = − │ g_x1│      H̃_xj = 2J̃_xjᵀJ̃_xj + x_j x_jᵀ + λI   (3×3)
       │  ⋮          ⋱         │ │ ⋮ │     │  ⋮  │      H̃_pp = 2Σ J̃_pjᵀJ̃_pj + λI          (P×P)
       └ H_pxNᵀ         H̃_xN  ┘ └ΔxN┘     └ g_xN┘      H_pxj = 2J̃_pjᵀJ̃_xj                 (P×3)

4. Schur complement (eq. 33–34): (H̃_pp − Σ H_pxj H̃_xj⁻¹ H_pxjᵀ) Δp = −g_p + Σ H_pxj H̃_xj⁻¹ g_xj,
   then Δx_j = H̃_xj⁻¹(−g_xj − H_pxjᵀ Δp): O(N) with 3×3 blocks.
5. Retraction x_j ← (x_j + Δx_j)/‖·‖ (eq. 31); accept if the cost falls (λ ← max(λ/10, 1e-14)),
   else λ ← min(10λ, 1e14) and retry (Algorithm 2, lines 25–38).

Stops after ``max_iter`` iterations or when the relative cost change falls below ``rtol``
(§III-A: 300 and 1e-6).

How the blocks are computed (same numbers, fewer operations). The Triggs correction is folded
into a per-sample weight matrix (:func:`~streamcal.fitting.kernels.triggs_weights`):
J̃ᵀJ̃ = Jᵀ W J and J̃ᵀr̃ = γ Jᵀr with W = w I + e r rᵀ. With A_j = J_xj (I − x_j x_jᵀ) the projected
direction Jacobian and B_j = A_jᵀ W_j (3×3):

    H_xj = 2 B_j A_j + x_j x_jᵀ,   g_xj = 2γ_j A_jᵀ r_j,   H_pxjᵀ = 2 B_j J_pj,
    S = Σ J_pjᵀ Q_j J_pj + λI,  Q_j = 2W_j − 4 B_jᵀ H̃_xj⁻¹ B_j,   rhs = Σ J_pjᵀ (−2γ_j r_j + 2 C_jᵀ g_xj),
    Δx_j = −H̃_xj⁻¹ g_xj − 2 C_j (J_pj Δp),   C_j = H̃_xj⁻¹ B_j,

so only 3×3 per-sample matrices are formed, stored structure-of-arrays ((3,3,N), (6,N) for the
unique entries of symmetric ones, contiguous along the samples) so every numpy call is one long
vectorized loop. For the core model (no effect, or effects with no ∂f/∂u) J_x = K; with no
effect J_pj = (x̄_jᵀ ⊗ I) E (x̄ = [x; 1], E selects the entries of [K b] that the structure frees),
so Σ J_pjᵀ Q_j J_pj = Eᵀ(Σ x̄_j x̄_jᵀ ⊗ Q_j)E is one (10,N)·(N,6) product and J_pj Δp = ΔK x_j + Δb:
the (N,3,P) Jacobian is never formed. The samples are processed in blocks of ``BLOCK`` (each
block's share of S and rhs summed, then its Δx) so the per-sample arrays stay in cache.
``tests/test_lm_equivalence.py`` checks the result against a literal transcription of steps 1–5.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from .kernels import L2, Cauchy, GemanMcClure, triggs_weights

LAMBDA_MIN, LAMBDA_MAX = 1e-14, 1e14
#: Entries of K (row, column) for each structure of the sensor matrix.
K_ENTRIES = {
    "full": ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
    "diag": ((0, 0), (1, 1), (2, 2)),
    "sphere": ((0, 0),),
}

# Symmetric 3×3 per-sample matrices are kept as their 6 unique entries, rows in this order.
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_SYM_I = np.array([i for i, _ in _SYM])
_SYM_J = np.array([j for _, j in _SYM])
_SYM_OF_FULL = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])        # row of _SYM for flat (a, b)
_FULL_OF_SYM = np.array([3 * i + j for i, j in _SYM])          # flat (a, b) of each _SYM row
_SYM_EYE = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])[:, None]
# cofactors of a symmetric [[a b c] [b d f'] [c f' g]] in _SYM order: co = H[P1]H[P2] − H[P3]H[P4]
_CO = np.array([[3, 5, 4, 4], [2, 4, 1, 5], [1, 4, 2, 3], [0, 5, 2, 2], [1, 2, 0, 4], [0, 3, 1, 1]]).T
# pairs (c, c') of x̄ = [x0 x1 x2 1] for Σ x̄ x̄ᵀ ⊗ Q, and the (12,12) index maps into them
_XBAR = tuple((c, d) for c in range(4) for d in range(c, 4))
_XBAR_I = np.array([c for c, _ in _XBAR])
_XBAR_J = np.array([d for _, d in _XBAR])
_PAIR4 = {**{p: n for n, p in enumerate(_XBAR)}, **{(d, c): n for n, (c, d) in enumerate(_XBAR)}}
_PAIR3 = {**{p: n for n, p in enumerate(_SYM)}, **{(j, i): n for n, (i, j) in enumerate(_SYM)}}
_GRAM_C = np.array([[_PAIR4[f // 3, g // 3] for g in range(12)] for f in range(12)])
_GRAM_I = np.array([[_PAIR3[f % 3, g % 3] for g in range(12)] for f in range(12)])
# (fancy indexing costs ~4x np.take on these small arrays: ~10 % of an LM iteration at N = 1000)
_GRAM_FLAT = _GRAM_C * len(_SYM) + _GRAM_I


@dataclass
class LMResult:
    """Outcome of :func:`refine`. Units are those of ``m`` (normalized in the pipeline)."""

    K: np.ndarray            # (3,3) upper triangular
    b: np.ndarray            # (3,)
    x: np.ndarray            # (N,3) unit directions
    thetas: list             # per effect, (P_e,) arrays
    residuals: np.ndarray    # (N,3) r_j at the solution
    weights: np.ndarray      # (N,) ρ′(s_j) — 1 for inliers, → 0 for outliers
    cost: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)
    #: :data:`streamcal.fitting.damped_lm.STATUSES`: ``converged`` (relative decrease below
    #: rtol), ``stalled`` (no trial step lowered the cost; ``converged`` is also True then, as
    #: it always was) or ``max_iter``; ``message`` in words.
    status: str = "max_iter"
    message: str = ""


def _k_vector(K: np.ndarray, structure: str) -> np.ndarray:
    return np.array([K[i, j] for i, j in K_ENTRIES[structure]])


def _k_matrix(k: np.ndarray, structure: str) -> np.ndarray:
    K = np.zeros((3, 3))
    if structure == "sphere":
        return np.eye(3) * k[0]
    for value, (i, j) in zip(k, K_ENTRIES[structure]):
        K[i, j] = value
    return K


def _jac_k(x: np.ndarray, structure: str) -> np.ndarray:
    """∂(K x)/∂k, shape (N,3,nk)."""
    n = x.shape[0]
    if structure == "sphere":
        return x[:, :, None].copy()
    entries = K_ENTRIES[structure]
    J = np.zeros((n, 3, len(entries)))
    for col, (i, j) in enumerate(entries):
        J[:, i, col] = x[:, j]
    return J


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3×3 matrices (N,3,3) by cofactors (faster than np.linalg.inv)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    co = np.empty_like(A)
    co[:, 0, 0] = e * i - f * h
    co[:, 0, 1] = c * h - b * i
    co[:, 0, 2] = b * f - c * e
    co[:, 1, 0] = f * g - d * i
    co[:, 1, 1] = a * i - c * g
    co[:, 1, 2] = c * d - a * f
    co[:, 2, 0] = d * h - e * g
    co[:, 2, 1] = b * g - a * h
    co[:, 2, 2] = a * e - b * d
    det = a * co[:, 0, 0] + b * co[:, 1, 0] + c * co[:, 2, 0]
    return co / det[:, None, None]


class _Model:
    """Residuals and Jacobians of the full model for one set of global parameters."""

    def __init__(self, m, structure, fit_b, effects, covariates):
        self.m = m
        self.structure = structure
        self.fit_b = fit_b
        self.effects = list(effects)
        self.cov = covariates
        self.nk = len(K_ENTRIES[structure])
        sizes = [e.n_params() for e in self.effects]
        self.theta_slices = []
        start = self.nk + (3 if fit_b else 0)
        for size in sizes:
            self.theta_slices.append(slice(start, start + size))
            start += size
        self.n_params = start

    def split(self, p):
        k = p[: self.nk]
        b = p[self.nk: self.nk + 3] if self.fit_b else None
        return k, b, [p[s] for s in self.theta_slices]

    def residual(self, K, b, thetas, x):
        u = x @ K.T
        r = u + b - self.m
        for effect, theta in zip(self.effects, thetas):
            r += effect.term(theta, u, self.cov)
        return r, u

    def jacobians(self, K, thetas, x, u):
        """J_p (N,3,P) and J_x (N,3,3), before robust weighting."""
        n = x.shape[0]
        G = None
        for effect, theta in zip(self.effects, thetas):
            ju = effect.jac_u(theta, u, self.cov)
            if ju is not None:
                G = ju + np.eye(3) if G is None else G + ju
        Jk = _jac_k(x, self.structure)
        parts = [Jk if G is None else G @ Jk]
        if self.fit_b:
            parts.append(np.broadcast_to(np.eye(3), (n, 3, 3)))
        for effect, theta in zip(self.effects, thetas):
            parts.append(effect.jac_theta(theta, u, self.cov))
        Jp = np.concatenate(parts, axis=2)
        Jx = np.broadcast_to(K, (n, 3, 3)) if G is None else G @ K
        return Jp, Jx


def _inv_sym(H6: np.ndarray) -> np.ndarray:
    """Inverses (6,N) of symmetric 3×3 matrices given by their unique entries H6 (6,N)."""
    co = H6.take(_CO[0], axis=0) * H6.take(_CO[1], axis=0)
    co -= H6.take(_CO[2], axis=0) * H6.take(_CO[3], axis=0)
    det = np.einsum("ik,ik->k", H6[:3], co[:3])
    co /= det
    return co


def _full(M6: np.ndarray) -> np.ndarray:
    """(3,3,N) symmetric matrices from their unique entries (6,N)."""
    return M6.take(_SYM_OF_FULL, axis=0).reshape(3, 3, -1)


def _sym(M9: np.ndarray) -> np.ndarray:
    """Unique entries (6,N) of (3,3,N) matrices known to be symmetric."""
    return M9.reshape(9, -1).take(_FULL_OF_SYM, axis=0)


#: Samples per block: one block's per-sample arrays ((3,3,8192) doubles = 0.6 MB each) stay in
#: cache between the numpy calls (at N = 1e5: ~25 % less time per iteration than unblocked).
BLOCK = 8192


_CORE_MAPS: dict = {}


def _core_map(structure: str, fit_b: bool) -> np.ndarray:
    """E (12,P): column f = 3c + i of the full map is ∂r/∂K[i, c] (c < 3) or ∂r/∂b[i] (c = 3);
    E picks (or, for K = kI, sums) the columns the structure frees. Built once per
    (structure, fit_b), read-only."""
    E = _CORE_MAPS.get((structure, fit_b))
    if E is None:
        E = _CORE_MAPS[structure, fit_b] = _build_core_map(structure, fit_b)
        E.setflags(write=False)
    return E


def _build_core_map(structure: str, fit_b: bool) -> np.ndarray:
    eye = np.eye(12)
    if structure == "sphere":
        cols = [eye[0] + eye[4] + eye[8]]
    else:
        cols = [eye[3 * j + i] for i, j in K_ENTRIES[structure]]
    if fit_b:
        cols.extend(eye[9:12])
    return np.column_stack(cols)


class _CoreJacobian:
    """J_pj = (x̄_jᵀ ⊗ I) E of the core model (no effect), x̄ = [x; 1], never formed."""

    def __init__(self, E: np.ndarray, x: np.ndarray):
        self.E, self.x = E, x
        self.xbar = np.vstack([x, np.ones((1, x.shape[1]))])
        self.xx = self.xbar.take(_XBAR_I, axis=0) * self.xbar.take(_XBAR_J, axis=0)

    def gram(self, Q6: np.ndarray) -> np.ndarray:
        """Σ J_pjᵀ Q_j J_pj (P,P) for symmetric Q (6,n)."""
        M = self.xx @ Q6.T
        return self.E.T @ M.take(_GRAM_FLAT) @ self.E

    def project(self, y: np.ndarray) -> np.ndarray:
        """Σ J_pjᵀ y_j (P,) for y (3,n)."""
        return self.E.T @ (self.xbar @ y.T).reshape(12)

    def apply(self, dp: np.ndarray) -> np.ndarray:
        """J_pj Δp = ΔK x_j + Δb, (3,n)."""
        full = self.E @ dp
        return full[:9].reshape(3, 3).T @ self.x + full[9:, None]


class _StackedJacobian:
    """J_p given as a stack (3,P,n) (models with effects)."""

    def __init__(self, Jp: np.ndarray):
        self.Jp = Jp

    def gram(self, Q6: np.ndarray) -> np.ndarray:
        QJ = np.einsum("abk,bpk->apk", _full(Q6), self.Jp)
        return np.einsum("apk,aqk->pq", self.Jp, QJ)

    def project(self, y: np.ndarray) -> np.ndarray:
        return np.einsum("apk,ak->p", self.Jp, y)

    def apply(self, dp: np.ndarray) -> np.ndarray:
        return np.einsum("apk,p->ak", self.Jp, dp)


class _Block:
    """One iteration's direction blocks for a run of samples (module docstring): built once per
    iteration, then :meth:`reduce` and :meth:`step` per damping trial."""

    def __init__(self, x, u, r, w, e, gw, K, Jx, jac, beta):
        if Jx is None:                                       # J_x = K, so J_x x = u
            A = K[:, :, None] - u[:, None, :] * x[None, :, :]
        else:
            A = Jx - np.einsum("abk,bk->ak", Jx, x)[:, None, :] * x[None, :, :]
        h = np.einsum("abk,ak->bk", A, r)                    # Aᵀ r
        self.B = w * A.transpose(1, 0, 2) + (e * h)[:, None, :] * r[None, :, :]   # Aᵀ W
        self.H6 = _sym(np.einsum("ack,cbk->abk", self.B, A))
        self.H6 *= 2.0
        self.H6 += beta * (x.take(_SYM_I, axis=0) * x.take(_SYM_J, axis=0))
        self.W2 = (2.0 * e) * (r.take(_SYM_I, axis=0) * r.take(_SYM_J, axis=0))
        self.W2 += 2.0 * w * _SYM_EYE
        self.gx = (2.0 * gw) * h
        self.y_r = (-2.0 * gw) * r
        self.jac = jac

    def reduce(self, lam: float):
        """This block's share of the Schur system at damping λ: (S (P,P), rhs (P,))."""
        self.Hinv = _full(_inv_sym(self.H6 + lam * _SYM_EYE))
        self.C = np.einsum("ack,cbk->abk", self.Hinv, self.B)          # H̃_x⁻¹ B
        Q6 = _sym(np.einsum("cak,cbk->abk", self.B, self.C))
        Q6 *= -4.0
        Q6 += self.W2
        y = self.y_r + 2.0 * np.einsum("abk,ak->bk", self.C, self.gx)
        return self.jac.gram(Q6), self.jac.project(y)

    def step(self, dp: np.ndarray) -> np.ndarray:
        """Δx (3,n) of the last :meth:`reduce`'s damping for the global step Δp."""
        dx = np.einsum("abk,bk->ak", self.C, self.jac.apply(dp))
        dx *= -2.0
        dx -= np.einsum("abk,bk->ak", self.Hinv, self.gx)
        return dx


#: A failed step that raises the cost by at most this fraction is rounding at the optimum.
FLAT = 1e-9


def refine(m: np.ndarray, K: np.ndarray, b: np.ndarray, x: np.ndarray, *, kernel=None,
           structure: str = "full", fit_b: bool = True, effects: Sequence = (),
           covariates: Mapping[str, np.ndarray] | None = None, thetas: Sequence | None = None,
           max_iter: int = 300, rtol: float = 1e-6, lam0: float = 10.0, max_trials: int = 12,
           beta: float = 1.0) -> LMResult:
    """Algorithm 2: robust LM over (K, b, θ, x_1…x_N) starting from a stage-1 model.

    Args:
        m: (N,3) measurements (normalized units in the pipeline).
        K, b, x: starting model (3,3), (3,) and unit directions (N,3).
        kernel: a kernel of :mod:`streamcal.fitting.kernels` (default L2).
        structure: ``"full"`` (upper-triangular K, soft iron), ``"diag"`` (scale only) or
            ``"sphere"`` (K = k I, hard iron only).
        fit_b: estimate b (else it stays as given).
        effects, covariates, thetas: extra effect terms, their covariates ((N,) arrays at the
            samples) and starting parameters (default ``effect.initial()``).
    """
    kernel = kernel or L2()
    rho = getattr(kernel, "rho", None) or (lambda s_: kernel.evaluate(s_)[0])
    m = np.asarray(m, dtype=float)
    cov = covariates or {}
    model = _Model(m, structure, fit_b, effects, cov)
    K = _k_matrix(_k_vector(np.asarray(K, dtype=float), structure), structure)
    b = np.asarray(b, dtype=float).copy()
    thetas = [np.asarray(t, dtype=float).copy() for t in (thetas or [e.initial() for e in model.effects])]
    # structure of arrays: samples along the last axis
    m_t = np.ascontiguousarray(m.T)
    x = np.array(np.asarray(x, dtype=float).T, order="C")
    n = x.shape[1]
    blocks = [slice(i, min(i + BLOCK, n)) for i in range(0, n, BLOCK)]
    eye_p = np.eye(model.n_params)
    E = _core_map(structure, fit_b) if not model.effects else None

    def cost_of(K_, b_, th_, x_):
        u_ = K_ @ x_
        r_ = u_ - m_t
        r_ += b_[:, None]
        for effect, theta in zip(model.effects, th_):
            r_ += effect.term(theta, u_.T, cov).T
        s_ = np.einsum("ak,ak->k", r_, r_)
        return float(np.sum(rho(s_))), r_, u_, s_

    f, r, u, s = cost_of(K, b, thetas, x)
    early = isinstance(kernel, (Cauchy, GemanMcClure))
    lam = lam0
    history = [f]
    converged = False
    iterations = 0
    status = "max_iter"
    for iterations in range(1, max_iter + 1):
        _, d1, d2 = kernel.evaluate(s)
        w, e, gw = triggs_weights(s, d1, d2)
        Jp = Jx = None
        if E is None:
            Jp, Jx = model.jacobians(K, thetas, x.T, u.T)
            Jp = np.ascontiguousarray(Jp.transpose(1, 2, 0))
            Jx = None if Jx.strides[0] == 0 else np.ascontiguousarray(Jx.transpose(1, 2, 0))
        parts = [_Block(x[:, sl], u[:, sl], r[:, sl], w[sl], e[sl], gw[sl], K,
                        None if Jx is None else Jx[:, :, sl],
                        _CoreJacobian(E, x[:, sl]) if Jp is None else _StackedJacobian(Jp[:, :, sl]),
                        beta) for sl in blocks]
        improved = False
        for _ in range(max_trials):
            S, rhs = lam * eye_p, 0.0
            for part in parts:
                S_part, rhs_part = part.reduce(lam)
                S = S + S_part
                rhs = rhs + rhs_part
            try:
                dp = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam = min(10 * lam, LAMBDA_MAX)
                continue
            x_new = np.empty_like(x)
            for sl, part in zip(blocks, parts):
                np.add(x[:, sl], part.step(dp), out=x_new[:, sl])
            x_new /= np.sqrt(np.einsum("ak,ak->k", x_new, x_new))
            dk, db, dth = model.split(dp)
            K_new = K + _k_matrix(dk, structure)
            b_new = b + db if fit_b else b
            th_new = [t + d for t, d in zip(thetas, dth)]
            f_new, r_new, u_new, s_new = cost_of(K_new, b_new, th_new, x_new)
            if np.isfinite(f_new) and f_new < f:
                improved = True
                rel = (f - f_new) / max(f, 1e-300)
                K, b, thetas, x, f, r, u, s = K_new, b_new, th_new, x_new, f_new, r_new, u_new, s_new
                lam = max(lam / 10, LAMBDA_MIN)
                break
            if early and np.isfinite(f_new) and f_new - f <= FLAT * f:
                # the step leaves the cost unchanged to rounding: at the optimum, stop instead
                # of trying max_trials λ. Only for the default fit's kernels (Cauchy,
                # Geman–McClure); L1's kink can hide a decrease behind a damped step, and L2 /
                # Huber keep the exhaustive search (their reference rows stay bit-for-bit).
                rel, improved = 0.0, True
                break
            lam = min(10 * lam, LAMBDA_MAX)
            if lam >= LAMBDA_MAX:
                break
        history.append(f)
        if not improved or rel < rtol:
            converged = True
            status = "stalled" if not improved else "converged"
            break
    weights = kernel.evaluate(s)[1]
    return LMResult(K=K, b=b, x=np.ascontiguousarray(x.T), thetas=thetas,
                    residuals=np.ascontiguousarray(r.T), weights=weights, cost=f,
                    iterations=iterations, converged=converged, history=history, status=status,
                    message={"stalled": f"no step lowered the cost in {max_trials} trials",
                             "converged": f"relative cost decrease below {rtol:g}",
                             "max_iter": f"{max_iter} iterations used"}[status])


def optimal_directions(K: np.ndarray, b: np.ndarray, m: np.ndarray, iters: int = 8) -> np.ndarray:
    """Unit directions x_j minimizing ‖K x_j + b − m_j‖ (eq. 41's inner problem), (N,3).

    Gauss–Newton on the sphere from x = K⁻¹(m − b)/‖·‖, vectorized over samples; a few
    iterations suffice because the start is within the noise of the optimum.
    """
    m = np.asarray(m, dtype=float)
    x = np.linalg.solve(K, (m - b).T).T
    x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
    n = m.shape[0]
    for _ in range(iters):
        r = x @ K.T + b - m
        P = np.eye(3) - x[:, :, None] * x[:, None, :]
        J = np.broadcast_to(K, (n, 3, 3)) @ P
        H = J.transpose(0, 2, 1) @ J + x[:, :, None] * x[:, None, :]
        g = np.einsum("nij,ni->nj", J, r)
        dx = -np.einsum("nij,nj->ni", _inv3(H), g)
        x = x + dx
        x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def estimation_error(K: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Per-sample sensor estimation error ‖K x̂_j + b − m_j‖ with x̂_j optimal (eq. 41), (N,)."""
    x = optimal_directions(K, b, m)
    return np.linalg.norm(x @ K.T + b - m, axis=1)
