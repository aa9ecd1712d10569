"""The per-sample work of one stage-2 LM iteration compiled into single loops (numba), for the
core model (K, b; no effect term) under the default fit's kernels (Cauchy, Geman–McClure).

The algebra is :mod:`streamcal.fitting.lm_blocks`' (same formulas, same order of the 3×3
products): the Triggs weights, A_j = K − u_j x_jᵀ, B_j = A_jᵀW_j, H̃_xj, its inverse, C_j =
H̃_xj⁻¹B_j, Q_j and the sample's share of the Schur system Σ x̄_j x̄_jᵀ ⊗ Q_j and Σ x̄_j ⊗ y_j.
Numpy needs about sixty calls per iteration over (3,3,N) temporaries for this; at N = 1000 the
calls' fixed cost, not the arithmetic, is most of the time (about 0.45 ms per iteration). One
compiled pass per damping trial keeps every per-sample quantity in registers.

Why not scipy.optimize.least_squares: it has no Schur elimination of the N direction blocks
(its Jacobian would be (3N, 3N + 9)), and the Triggs-corrected kernels and the paper's damping
schedule are part of the method's published behaviour (``tests/test_lm_equivalence.py``).

Chosen with ``STREAMCAL_LM_ENGINE=compiled`` (:data:`streamcal.fitting.lm.ENGINE_ENV`). numba is
imported on first use (with loading the cached code ~0.4 s and ~100 MB resident); the loops are
compiled once (a few seconds) and cached on disk. Without numba the numpy engine runs (same
results to rounding).
"""
from __future__ import annotations

import numpy as np

from .kernels import D_MIN, Cauchy, GemanMcClure
from .lm_blocks import _GRAM_FLAT, _core_map

#: Kernel ids inside the compiled loops.
_KERNEL_IDS = {Cauchy: 0, GemanMcClure: 1}
_COMPILED = None
NO_NUMBA = "numba is not installed"


def _numba():
    try:
        import numba
    except ImportError:  # an optional accelerator: the numpy engine gives the same results
        return None
    return numba


def why_not(model, kernel) -> str:
    """Why the compiled engine does not apply ('' when it does)."""
    if model.effects:
        return "the model has effect terms"
    if type(kernel) not in _KERNEL_IDS:
        return f"kernel {getattr(kernel, 'name', kernel)!r} (only cauchy and gm are compiled)"
    if _compiled() is None:
        return NO_NUMBA
    return ""


def _compiled():
    """The compiled loops (built on first use), or None without numba."""
    global _COMPILED
    if _COMPILED is None:
        numba = _numba()
        if numba is None:
            return None
        # error_model "numpy": a division by zero gives inf/nan (a rejected step), as in numpy
        jit = numba.njit(cache=True, nogil=True, error_model="numpy")
        _COMPILED = (jit(_reduce_core), jit(_step_core), jit(_cost_core), jit(_solve))
    return _COMPILED


def _solve(S, rhs):
    """np.linalg.solve of the (P,P) Schur system without numpy's per-call overhead (~15 µs of
    an iteration's ~100 at N = 1000); raises LinAlgError when S is singular, like numpy."""
    return np.linalg.solve(S, rhs)


def _cost_core(m, x, K, b, kid, t2):
    """Σ ρ(‖K x_j + b − m_j‖²) over the samples; m, x (3,N)."""
    total = 0.0
    for j in range(m.shape[1]):
        s = 0.0
        for a in range(3):
            r = K[a, 0] * x[0, j] + K[a, 1] * x[1, j] + K[a, 2] * x[2, j] + b[a] - m[a, j]
            s += r * r
        if kid == 0:
            total += t2 * np.log1p(s / t2)
        else:
            total += s * t2 / (t2 + s)
    return total


def _step_core(x, C, Hg, dK, db, x_out):
    """x_out (3,N) = retraction of x + Δx, Δx_j = −2 C_j (ΔK x_j + Δb) − H̃_xj⁻¹ g_xj."""
    jd = np.empty(3)
    for j in range(x.shape[1]):
        for a in range(3):
            jd[a] = dK[a, 0] * x[0, j] + dK[a, 1] * x[1, j] + dK[a, 2] * x[2, j] + db[a]
        norm = 0.0
        for a in range(3):
            cj = C[j, 3 * a] * jd[0] + C[j, 3 * a + 1] * jd[1] + C[j, 3 * a + 2] * jd[2]
            v = x[a, j] - 2.0 * cj - Hg[j, a]
            x_out[a, j] = v
            norm += v * v
        norm = np.sqrt(norm)
        for a in range(3):
            x_out[a, j] /= norm


def _reduce_core(m, x, K, b, kid, t2, beta, lam, C, Hg, T, G):
    """The Schur system's per-sample sums at damping λ, and what the step needs.

    m, x (3,N); K (3,3); b (3,). Writes C (N,9) = H̃_x⁻¹B row-major, Hg (N,3) = H̃_x⁻¹g_x,
    T (10,6) = Σ x̄_c x̄_d Q_j (pairs c ≤ d of x̄ = [x; 1], Q's unique entries) and
    G (4,3) = Σ x̄_c y_j. Every 3×3 is spelled out in scalars (entry ac = row a, column c): in
    small arrays LLVM keeps reloading them, which tripled the time."""
    k00, k01, k02, k10, k11, k12, k20, k21, k22 = (K[0, 0], K[0, 1], K[0, 2], K[1, 0], K[1, 1],
                                                   K[1, 2], K[2, 0], K[2, 1], K[2, 2])
    acc = np.zeros(72)                    # T (10,6) then G (4,3), summed locally
    q = np.empty(6)
    yv = np.empty(3)
    xb = np.empty(4)
    xb[3] = 1.0
    for j in range(m.shape[1]):
        x0, x1, x2 = x[0, j], x[1, j], x[2, j]
        u0 = k00 * x0 + k01 * x1 + k02 * x2
        u1 = k10 * x0 + k11 * x1 + k12 * x2
        u2 = k20 * x0 + k21 * x1 + k22 * x2
        r0, r1, r2 = u0 + b[0] - m[0, j], u1 + b[1] - m[1, j], u2 + b[2] - m[2, j]
        s = r0 * r0 + r1 * r1 + r2 * r2
        if kid == 0:                                  # Cauchy: ρ = t2 log(1 + s/t2)
            qq = 1.0 + s / t2
            d1, d2 = 1.0 / qq, -1.0 / (t2 * qq * qq)
        else:                                         # Geman–McClure: ρ = s t2 / (t2 + s)
            qq = t2 + s
            d1, d2 = t2 * t2 / (qq * qq), -2.0 * t2 * t2 / (qq * qq * qq)
        # Triggs weights (kernels.triggs_weights): W = w I + e r rᵀ, gradient scale gw
        w = max(d1, 1e-300)
        if s > 1e-12:
            e, gw = max(2.0 * d2, (D_MIN - 1.0) * w / s), w
        else:
            e, gw = 0.0, w / np.sqrt(max(1.0 + 2.0 * s * d2 / w, D_MIN))
        # A = K − u xᵀ, h = Aᵀ r
        a00, a01, a02 = k00 - u0 * x0, k01 - u0 * x1, k02 - u0 * x2
        a10, a11, a12 = k10 - u1 * x0, k11 - u1 * x1, k12 - u1 * x2
        a20, a21, a22 = k20 - u2 * x0, k21 - u2 * x1, k22 - u2 * x2
        h0 = a00 * r0 + a10 * r1 + a20 * r2
        h1 = a01 * r0 + a11 * r1 + a21 * r2
        h2 = a02 * r0 + a12 * r1 + a22 * r2
        # B = w Aᵀ + e h rᵀ
        b00, b01, b02 = w * a00 + e * h0 * r0, w * a10 + e * h0 * r1, w * a20 + e * h0 * r2
        b10, b11, b12 = w * a01 + e * h1 * r0, w * a11 + e * h1 * r1, w * a21 + e * h1 * r2
        b20, b21, b22 = w * a02 + e * h2 * r0, w * a12 + e * h2 * r1, w * a22 + e * h2 * r2
        # H̃ = 2 B A + β x xᵀ + λ I (symmetric)
        H0 = 2.0 * (b00 * a00 + b01 * a10 + b02 * a20) + beta * (x0 * x0) + lam
        H1 = 2.0 * (b00 * a01 + b01 * a11 + b02 * a21) + beta * (x0 * x1)
        H2 = 2.0 * (b00 * a02 + b01 * a12 + b02 * a22) + beta * (x0 * x2)
        H3 = 2.0 * (b10 * a01 + b11 * a11 + b12 * a21) + beta * (x1 * x1) + lam
        H4 = 2.0 * (b10 * a02 + b11 * a12 + b12 * a22) + beta * (x1 * x2)
        H5 = 2.0 * (b20 * a02 + b21 * a12 + b22 * a22) + beta * (x2 * x2) + lam
        c0 = H3 * H5 - H4 * H4
        c1 = H2 * H4 - H1 * H5
        c2 = H1 * H4 - H2 * H3
        c3 = H0 * H5 - H2 * H2
        c4 = H1 * H2 - H0 * H4
        c5 = H0 * H3 - H1 * H1
        det = H0 * c0 + H1 * c1 + H2 * c2
        i00, i01, i02, i11, i12, i22 = c0 / det, c1 / det, c2 / det, c3 / det, c4 / det, c5 / det
        g0, g1, g2 = 2.0 * gw * h0, 2.0 * gw * h1, 2.0 * gw * h2
        # C = H̃⁻¹ B, and H̃⁻¹ g_x
        e00 = i00 * b00 + i01 * b10 + i02 * b20
        e01 = i00 * b01 + i01 * b11 + i02 * b21
        e02 = i00 * b02 + i01 * b12 + i02 * b22
        e10 = i01 * b00 + i11 * b10 + i12 * b20
        e11 = i01 * b01 + i11 * b11 + i12 * b21
        e12 = i01 * b02 + i11 * b12 + i12 * b22
        e20 = i02 * b00 + i12 * b10 + i22 * b20
        e21 = i02 * b01 + i12 * b11 + i22 * b21
        e22 = i02 * b02 + i12 * b12 + i22 * b22
        C[j, 0], C[j, 1], C[j, 2] = e00, e01, e02
        C[j, 3], C[j, 4], C[j, 5] = e10, e11, e12
        C[j, 6], C[j, 7], C[j, 8] = e20, e21, e22
        Hg[j, 0] = i00 * g0 + i01 * g1 + i02 * g2
        Hg[j, 1] = i01 * g0 + i11 * g1 + i12 * g2
        Hg[j, 2] = i02 * g0 + i12 * g1 + i22 * g2
        # Q = 2W − 4 Bᵀ C (symmetric), y = −2γ r + 2 Cᵀ g_x
        we = 2.0 * e
        q[0] = -4.0 * (b00 * e00 + b10 * e10 + b20 * e20) + we * r0 * r0 + 2.0 * w
        q[1] = -4.0 * (b00 * e01 + b10 * e11 + b20 * e21) + we * r0 * r1
        q[2] = -4.0 * (b00 * e02 + b10 * e12 + b20 * e22) + we * r0 * r2
        q[3] = -4.0 * (b01 * e01 + b11 * e11 + b21 * e21) + we * r1 * r1 + 2.0 * w
        q[4] = -4.0 * (b01 * e02 + b11 * e12 + b21 * e22) + we * r1 * r2
        q[5] = -4.0 * (b02 * e02 + b12 * e12 + b22 * e22) + we * r2 * r2 + 2.0 * w
        yv[0] = -2.0 * gw * r0 + 2.0 * (e00 * g0 + e10 * g1 + e20 * g2)
        yv[1] = -2.0 * gw * r1 + 2.0 * (e01 * g0 + e11 * g1 + e21 * g2)
        yv[2] = -2.0 * gw * r2 + 2.0 * (e02 * g0 + e12 * g1 + e22 * g2)
        xb[0], xb[1], xb[2] = x0, x1, x2
        n = 0
        for c in range(4):
            for d in range(c, 4):
                xx = xb[c] * xb[d]
                for k in range(6):
                    acc[6 * n + k] += xx * q[k]
                n += 1
            for k in range(3):
                acc[60 + 3 * c + k] += xb[c] * yv[k]
    for k in range(60):
        T[k // 6, k % 6] = acc[k]
    for k in range(12):
        G[k // 3, k % 3] = acc[60 + k]


def warm_up() -> bool:
    """Compile (or load from numba's cache) every loop now, on a tiny problem; False without
    numba. The first compilation after installation takes a few seconds; CI does it once before
    the tests so that no test waits for it."""
    compiled = _compiled()
    if compiled is None:
        return False
    reduce_core, step_core, cost_core, solve = compiled
    n = 4
    m = np.array([[1.0, 0.0, 0.0, 0.6], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.8]])
    K, b = np.eye(3), np.zeros(3)
    C, Hg, T, G = np.empty((n, 9)), np.empty((n, 3)), np.empty((10, 6)), np.empty((4, 3))
    for kid in (0, 1):
        cost_core(m, m, K, b, kid, 1.0)
        reduce_core(m, m, K, b, kid, 1.0, 1.0, 1.0, C, Hg, T, G)
    step_core(m, C, Hg, K, b, np.empty_like(m))
    solve(np.eye(3), b)
    return True


class FusedEngine:
    """:class:`~streamcal.fitting.lm_blocks.NumpyEngine`'s interface over the compiled loops."""

    def __init__(self, model, m_t: np.ndarray, kernel, beta: float):
        self.reduce_core, self.step_core, self.cost_core, self.solve = _compiled()
        self.m_t = m_t
        self.kid = _KERNEL_IDS[type(kernel)]
        self.t2 = float(kernel.tau) ** 2
        self.beta = float(beta)
        self.E = _core_map(model.structure, model.fit_b)
        n = m_t.shape[1]
        self.C = np.empty((n, 9))
        self.Hg = np.empty((n, 3))
        self.T = np.empty((10, 6))
        self.G = np.empty((4, 3))
        self.eye_p = np.eye(model.n_params)

    def cost(self, K, b, thetas, x):
        return self.cost_core(self.m_t, x, K, b, self.kid, self.t2), None

    def linearize(self, K, b, thetas, x, state) -> None:
        self.K, self.b, self.x = K, b, x

    def reduce(self, lam: float):
        self.reduce_core(self.m_t, self.x, self.K, self.b, self.kid, self.t2, self.beta, float(lam),
                         self.C, self.Hg, self.T, self.G)
        S = self.E.T @ self.T.take(_GRAM_FLAT) @ self.E
        return lam * self.eye_p + S, self.E.T @ self.G.reshape(12)

    def step(self, x, dp):
        full = self.E @ dp
        x_new = np.empty_like(x)
        self.step_core(x, self.C, self.Hg, np.ascontiguousarray(full[:9].reshape(3, 3).T),
                       full[9:].copy(), x_new)
        return x_new

    def residuals(self, K, b, thetas, x, state):
        r = K @ x - self.m_t
        r += b[:, None]
        return r, np.einsum("ak,ak->k", r, r)
