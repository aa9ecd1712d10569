"""The per-sample block algebra of stage 2's LM in numpy (:class:`NumpyEngine`), for every
model; :mod:`streamcal.fitting.lm` runs the iterations.

How the blocks are computed (same numbers as the paper's 3×3 blocks, fewer operations). The
Triggs correction is folded into a per-sample weight matrix
(:func:`~streamcal.fitting.kernels.triggs_weights`): J̃ᵀJ̃ = Jᵀ W J and J̃ᵀr̃ = γ Jᵀr with
W = w I + e r rᵀ. With A_j = J_xj (I − x_j x_jᵀ) the projected direction Jacobian, the paper's
direction block is H̃_xj = 2 A_jᵀ W_j A_j + β x_j x_jᵀ + λI, its gradient g_xj = 2γ_j A_jᵀ r_j and
the coupling H_pxjᵀ = 2 A_jᵀ W_j J_pj. Since A_j x_j = 0, H̃_xj maps x_j to (β + λ) x_j and the
tangent plane to itself, while g_xj and H_pxjᵀ lie in the tangent plane: the step has no
component along x_j, and everything is solved in an orthonormal tangent basis T_j (3×2, from
:func:`_tangent_basis`), with D_j = J_xj T_j and F_j = W_j D_j (3×2):

    H_tj = 2 D_jᵀ W_j D_j + λI (2×2),   g_tj = 2γ_j D_jᵀ r_j,
    S = Σ J_pjᵀ Q_j J_pj + λI,  Q_j = 2W_j − 4 F_j H_tj⁻¹ F_jᵀ,   rhs = Σ J_pjᵀ (−2γ_j r_j + 2 F_j z_j),
    Δx_j = −T_j (z_j + 2 C_j (J_pj Δp)),   z_j = H_tj⁻¹ g_tj,   C_j = H_tj⁻¹ F_jᵀ,

exactly the paper's Schur complement (eq. 33–34) with 2×2 inverses in place of 3×3 ones (β,
the gauge along x_j, drops out). Per-sample matrices are stored structure-of-arrays ((3,2,N),
(3,N) for a symmetric 2×2, (6,N) for a symmetric 3×3, contiguous along the samples) so every
numpy call is one long vectorized loop. For the core model (no effect, or effects with no
∂f/∂u) J_x = K; with no effect J_pj = (x̄_jᵀ ⊗ I) E (x̄ = [x; 1], E selects the entries of [K b]
that the structure frees), so Σ J_pjᵀ Q_j J_pj = Eᵀ(Σ x̄_j x̄_jᵀ ⊗ Q_j)E is one (10,N)·(N,6)
product and J_pj Δp = ΔK x_j + Δb: the (N,3,P) Jacobian is never formed. The samples are
processed in blocks of ``BLOCK`` (each block's share of S and rhs summed, then its Δx) so the
per-sample arrays stay in cache. ``tests/test_lm_equivalence.py`` checks every model against a
literal transcription of the paper's 3×3 algebra.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dgesv

from .kernels import derivatives_of, triggs_weights

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
_SYM_EYE = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])[:, None]
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


def _full(M6: np.ndarray) -> np.ndarray:
    """(3,3,N) symmetric matrices from their unique entries (6,N)."""
    return M6.take(_SYM_OF_FULL, axis=0).reshape(3, 3, -1)


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
        self.xbar = np.empty((4, x.shape[1]))
        self.xbar[:3] = x
        self.xbar[3] = 1.0
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


def _tangent_basis(x: np.ndarray) -> np.ndarray:
    """Orthonormal tangent vectors T (3,2,N) at unit directions x (3,N), T[:, i] ⟂ x: the
    branch-free basis of Duff et al., "Building an orthonormal basis, revisited" (JCGT 2017)."""
    x0, x1, x2 = x
    sg = np.copysign(1.0, x2)
    a = -1.0 / (sg + x2)
    bb = x0 * x1 * a
    sx = sg * x0
    T = np.empty((3, 2, x.shape[1]))
    np.multiply(sx * x0, a, out=T[0, 0])
    T[0, 0] += 1.0
    np.multiply(sg, bb, out=T[1, 0])
    np.negative(sx, out=T[2, 0])
    T[0, 1] = bb
    np.multiply(x1 * x1, a, out=T[1, 1])
    T[1, 1] += sg
    np.negative(x1, out=T[2, 1])
    return T


# (2,2) symmetric per-sample matrices as their unique entries (11, 12, 22)
_T2_I, _T2_J = np.array([0, 0, 1]), np.array([0, 1, 1])
_EYE2 = np.array([1.0, 0.0, 1.0])[:, None]
_INV2, _INV2_SIGN = np.array([2, 1, 1, 0]), np.array([1.0, -1.0, -1.0, 1.0])[:, None]


class _Block:
    """One iteration's direction blocks for a run of samples, in each direction's tangent plane
    (module docstring): built once per iteration, then :meth:`reduce` and :meth:`step` per
    damping trial."""

    def __init__(self, x, u, r, w, e, gw, K, Jx, jac):
        self.T = T = _tangent_basis(x)
        n = x.shape[1]
        if Jx is None:                                       # J_x = K
            D = (K @ T.reshape(3, 2 * n)).reshape(3, 2, n)
        else:
            D = np.einsum("abk,bik->aik", Jx, T)
        Dr = np.einsum("aik,ak->ik", D, r)                   # Dᵀ r (2,n)
        H3 = np.einsum("aik,aik->ik", D.take(_T2_I, axis=1), D.take(_T2_J, axis=1))
        H3 *= 2.0 * w
        H3 += (2.0 * e) * (Dr.take(_T2_I, axis=0) * Dr.take(_T2_J, axis=0))
        self.H3 = H3                                         # 2 Dᵀ W D (3,n)
        self.F = w * D + (e * r)[:, None, :] * Dr[None, :, :]    # W D (3,2,n)
        self.W2 = (2.0 * e) * (r.take(_SYM_I, axis=0) * r.take(_SYM_J, axis=0))
        self.W2 += 2.0 * w * _SYM_EYE
        self.gt = (2.0 * gw) * Dr                            # Tᵀ g_x
        self.y_r = (-2.0 * gw) * r
        self.jac = jac

    def reduce(self, lam: float):
        """This block's share of the Schur system at damping λ: (S (P,P), rhs (P,))."""
        H = self.H3 + lam * _EYE2
        det = H[0] * H[2]
        det -= H[1] * H[1]
        Hinv = H.take(_INV2, axis=0)
        Hinv *= _INV2_SIGN
        Hinv /= det
        Hinv = Hinv.reshape(2, 2, -1)                        # H_t⁻¹ (2,2,n)
        self.C = np.einsum("ijk,ajk->iak", Hinv, self.F)     # H_t⁻¹ Fᵀ (2,3,n)
        self.z = np.einsum("ijk,jk->ik", Hinv, self.gt)      # H_t⁻¹ Tᵀ g_x (2,n)
        Q6 = np.einsum("cik,ick->ck", self.F.take(_SYM_I, axis=0), self.C.take(_SYM_J, axis=1))
        Q6 *= -4.0
        Q6 += self.W2
        y = np.einsum("aik,ik->ak", self.F, self.z)
        y *= 2.0
        y += self.y_r
        return self.jac.gram(Q6), self.jac.project(y)

    def step(self, dp: np.ndarray) -> np.ndarray:
        """Δx (3,n) of the last :meth:`reduce`'s damping for the global step Δp."""
        dt = np.einsum("iak,ak->ik", self.C, self.jac.apply(dp))
        dt *= 2.0
        dt += self.z
        dx = np.einsum("aik,ik->ak", self.T, dt)
        np.negative(dx, out=dx)
        return dx


_EYES: dict = {}


def _eye(n: int) -> np.ndarray:
    """np.eye(n), built once per size, read-only."""
    eye = _EYES.get(n)
    if eye is None:
        eye = _EYES[n] = np.eye(n)
        eye.setflags(write=False)
    return eye


class NumpyEngine:
    """One LM iteration's per-sample algebra in numpy, for any model (effects included).

    ``cost`` evaluates a state; ``linearize`` builds the direction blocks at the accepted
    state; ``reduce(λ)`` returns the damped Schur system; ``step`` the retracted directions;
    ``final`` the residuals, their norms and weights at the end."""

    def __init__(self, model, m_t: np.ndarray, kernel):
        self.model, self.m_t, self.kernel = model, m_t, kernel
        self.rho = getattr(kernel, "rho", None) or (lambda s_: kernel.evaluate(s_)[0])
        self.derivatives = derivatives_of(kernel)
        self.E = _core_map(model.structure, model.fit_b) if not model.effects else None
        n = m_t.shape[1]
        self.slices = [slice(i, min(i + BLOCK, n)) for i in range(0, n, BLOCK)]
        self.eye_p = _eye(model.n_params)

    def cost(self, K, b, thetas, x):
        """(Σ ρ(‖r_j‖²), state) at directions x (3,N); the state is (r (3,N), u (3,N), s (N,))."""
        u = K @ x
        r = u - self.m_t
        r += b[:, None]
        for effect, theta in zip(self.model.effects, thetas):
            r += effect.term(theta, u.T, self.model.cov).T
        s = np.einsum("ak,ak->k", r, r)
        return float(np.sum(self.rho(s))), (r, u, s)

    def linearize(self, K, b, thetas, x, state) -> None:
        r, u, s = state
        d1, d2 = self.derivatives(s)
        w, e, gw = triggs_weights(s, d1, d2)
        jp = jx = None
        if self.E is None:
            jp, jx = self.model.jacobians(K, thetas, x.T, u.T)
            jp = np.ascontiguousarray(jp.transpose(1, 2, 0))
            jx = None if jx.strides[0] == 0 else np.ascontiguousarray(jx.transpose(1, 2, 0))
        self.parts = [_Block(x[:, sl], u[:, sl], r[:, sl], w[sl], e[sl], gw[sl], K,
                             None if jx is None else jx[:, :, sl],
                             _CoreJacobian(self.E, x[:, sl]) if jp is None
                             else _StackedJacobian(jp[:, :, sl]))
                      for sl in self.slices]

    def reduce(self, lam: float):
        """(S + λI (P,P), rhs (P,)) of the Schur system at damping λ."""
        S, rhs = lam * self.eye_p, 0.0
        for part in self.parts:
            S_part, rhs_part = part.reduce(lam)
            S = S + S_part
            rhs = rhs + rhs_part
        return S, rhs

    @staticmethod
    def solve(S, rhs):
        """Δp (P,) of the damped system; LinAlgError when S is singular. LAPACK's dgesv (the
        routine np.linalg.solve runs) called directly: numpy's wrapper costs ~4× the solve."""
        _, _, dp, info = dgesv(S, rhs)
        if info:
            raise np.linalg.LinAlgError(f"the damped Schur system is singular (dgesv info {info})")
        return dp

    def step(self, x, dp):
        """Directions (3,N) after the global step Δp and its Δx, retracted to the sphere."""
        x_new = np.empty_like(x)
        for sl, part in zip(self.slices, self.parts):
            np.add(x[:, sl], part.step(dp), out=x_new[:, sl])
        x_new /= np.sqrt(np.einsum("ak,ak->k", x_new, x_new))
        return x_new

    def final(self, K, b, thetas, x, state):
        """(r (N,3), ‖r‖ (N,), ρ′(‖r‖²) (N,)) of the state."""
        r, _, s = state
        return np.ascontiguousarray(r.T), np.sqrt(s), self.derivatives(s)[0]
