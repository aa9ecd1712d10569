"""The optimized LM (``streamcal.fitting.lm.refine``) against a slow reference: a literal
transcription of Algorithm 2 with the formulas the LM used before it was restructured (stacked
(N,3,P) Triggs-corrected Jacobians, tangent projection, 3×3 block Hessians, Schur complement
with explicit block inverses). Both must reach the same K, b, θ, x and cost to ~1e-10 relative,
with the same number of iterations, for every kernel, every structure of K, and with an additive
effect and an effect whose term depends on u (∂f/∂u ≠ 0).
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from streamcal.fitting import kernels, lm, lm_compiled
from streamcal.fitting.lm import K_ENTRIES, LAMBDA_MAX, LAMBDA_MIN, refine

RTOL = 1e-10


# -- the reference --------------------------------------------------------------------------------
def _k_vector(K, structure):
    return np.array([K[i, j] for i, j in K_ENTRIES[structure]])


def _k_matrix(k, structure):
    if structure == "sphere":
        return np.eye(3) * k[0]
    K = np.zeros((3, 3))
    for value, (i, j) in zip(k, K_ENTRIES[structure]):
        K[i, j] = value
    return K


def _jac_k(x, structure):
    """∂(K x)/∂k, (N,3,nk)."""
    if structure == "sphere":
        return x[:, :, None].copy()
    entries = K_ENTRIES[structure]
    J = np.zeros((x.shape[0], 3, len(entries)))
    for col, (i, j) in enumerate(entries):
        J[:, i, col] = x[:, j]
    return J


def reference_refine(m, K, b, x, *, kernel, structure="full", effects=(), cov=None, thetas=None,
                     max_iter=300, rtol=1e-6, lam0=10.0, max_trials=12, beta=1.0):
    """Algorithm 2 written out step by step (fit_b = True); returns (K, b, θ, x, cost, its)."""
    cov = cov or {}
    n = m.shape[0]
    nk = len(K_ENTRIES[structure])
    K = _k_matrix(_k_vector(K, structure), structure)
    b, x = b.copy(), x.copy()
    thetas = [np.asarray(t, float).copy() for t in (thetas or [e.initial() for e in effects])]
    sizes = [e.n_params() for e in effects]
    P = nk + 3 + sum(sizes)

    def residual(K_, b_, th_, x_):
        u_ = x_ @ K_.T
        r_ = u_ + b_ - m
        for eff, th in zip(effects, th_):
            r_ = r_ + eff.term(th, u_, cov)
        return r_, u_

    def cost(K_, b_, th_, x_):
        r_, u_ = residual(K_, b_, th_, x_)
        s_ = np.einsum("ij,ij->i", r_, r_)
        return float(np.sum(kernel.evaluate(s_)[0])), r_, u_, s_

    f, r, u, s = cost(K, b, thetas, x)
    lam, rel = lam0, np.inf
    for it in range(1, max_iter + 1):
        # 1. kernel and Triggs correction (eq. 22–24)
        _, d1, d2 = kernel.evaluate(s)
        r_scale, j_alpha, sqrt_d1 = kernels.triggs_correction(s, d1, d2)
        # model Jacobians: G = I + Σ ∂f/∂u; J_p = [G J_k, I, ∂f/∂θ], J_x = G K
        G = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        for eff, th in zip(effects, thetas):
            ju = eff.jac_u(th, u, cov)
            if ju is not None:
                G = G + ju
        parts = [G @ _jac_k(x, structure), np.broadcast_to(np.eye(3), (n, 3, 3))]
        parts += [eff.jac_theta(th, u, cov) for eff, th in zip(effects, thetas)]
        Jp = np.concatenate(parts, axis=2)
        Jx = G @ K
        # J̃ = √ρ′ (I − α r rᵀ/‖r‖²) J, r̃ = r_scale r
        M = np.eye(3)[None] - j_alpha[:, None, None] * (r[:, :, None] * r[:, None, :])
        Jp_t = sqrt_d1[:, None, None] * (M @ Jp)
        Jx_t = sqrt_d1[:, None, None] * (M @ Jx)
        # 2. tangent projection (eq. 27)
        Jx_t = Jx_t @ (np.eye(3)[None] - x[:, :, None] * x[:, None, :])
        rt = r_scale[:, None] * r
        # 3. blocks (eq. 25–26, 30)
        Hxx = 2.0 * np.transpose(Jx_t, (0, 2, 1)) @ Jx_t + beta * (x[:, :, None] * x[:, None, :])
        Hpx = 2.0 * np.transpose(Jp_t, (0, 2, 1)) @ Jx_t                   # (N,P,3)
        Hpp = 2.0 * np.einsum("nap,naq->pq", Jp_t, Jp_t)
        gp = 2.0 * np.einsum("nap,na->p", Jp_t, rt)
        gx = 2.0 * np.einsum("nab,na->nb", Jx_t, rt)
        improved = False
        for _ in range(max_trials):
            # 4. Schur complement (eq. 33–34)
            Hxx_inv = np.linalg.inv(Hxx + lam * np.eye(3)[None])
            S = Hpp + lam * np.eye(P) - np.einsum("npa,nab,nqb->pq", Hpx, Hxx_inv, Hpx)
            rhs = -gp + np.einsum("npa,nab,nb->p", Hpx, Hxx_inv, gx)
            try:
                dp = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam = min(10 * lam, LAMBDA_MAX)
                continue
            dx = -np.einsum("nab,nb->na", Hxx_inv, gx + np.einsum("npa,p->na", Hpx, dp))
            # 5. update, retraction (eq. 31), acceptance
            K_new = K + _k_matrix(dp[:nk], structure)
            b_new = b + dp[nk:nk + 3]
            th_new, start = [], nk + 3
            for t, size in zip(thetas, sizes):
                th_new.append(t + dp[start:start + size])
                start += size
            x_new = x + dx
            x_new /= np.linalg.norm(x_new, axis=1, keepdims=True)
            f_new, r_new, u_new, s_new = cost(K_new, b_new, th_new, x_new)
            if np.isfinite(f_new) and f_new < f:
                improved = True
                rel = (f - f_new) / max(f, 1e-300)
                K, b, thetas, x, f, r, u, s = K_new, b_new, th_new, x_new, f_new, r_new, u_new, s_new
                lam = max(lam / 10, LAMBDA_MIN)
                break
            lam = min(10 * lam, LAMBDA_MAX)
            if lam >= LAMBDA_MAX:
                break
        if not improved or rel < rtol:
            break
    return K, b, thetas, x, f, it


# -- a fixed problem ------------------------------------------------------------------------------
def problem(structure, seed=3, n=240, eta=0.1):
    """Normalized-scale data from a known model, a fraction η of gross outliers, and a start
    perturbed from the truth (directions from the perturbed model)."""
    rng = np.random.default_rng(seed)
    K = np.eye(3) + 0.1 * np.triu(rng.standard_normal((3, 3)))
    if structure == "diag":
        K = np.diag(np.diag(K))
    elif structure == "sphere":
        K = np.eye(3) * K[0, 0]
    b = 0.2 * rng.standard_normal(3)
    x = rng.standard_normal((n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = x @ K.T + b + 0.01 * rng.standard_normal((n, 3))
    bad = rng.random(n) < eta
    m[bad] += rng.uniform(-0.5, 0.5, (bad.sum(), 3))
    K0 = K + 0.03 * np.triu(rng.standard_normal((3, 3)))
    b0 = b + 0.03 * rng.standard_normal(3)
    x0 = np.linalg.solve(K0, (m - b0).T).T
    x0 /= np.linalg.norm(x0, axis=1, keepdims=True)
    cov = {"temp": 20.0 + 5.0 * rng.standard_normal(n), "t": np.linspace(0.0, 100.0, n)}
    return m, K0, b0, x0, cov


def make(name):
    return kernels.make_kernel(name, 0.03 if name in kernels.WIDTH_KERNELS else None)


def assert_same(got, ref):
    K, b, thetas, x, f, its = ref
    np.testing.assert_allclose(got.K, K, rtol=RTOL, atol=RTOL * np.abs(K).max())
    np.testing.assert_allclose(got.b, b, rtol=RTOL, atol=RTOL * np.abs(K).max())
    # A direction's block H_xj has its tangent part ∝ ρ′_j: rounding differences are amplified
    # by 1/ρ′_j where a redescending kernel all but ignores an outlier (GM: ρ′ ~ 1e-6 gives
    # ~1e-8 between any two orderings of the same sums, the old code's included).
    tol = RTOL / np.minimum(1.0, got.weights)
    assert np.all(np.abs(got.x - x).max(axis=1) <= tol)
    for t_got, t_ref in zip(got.thetas, thetas):
        np.testing.assert_allclose(t_got, t_ref, rtol=1e-8, atol=RTOL * np.abs(K).max())
    assert got.cost == pytest.approx(f, rel=RTOL)
    assert got.iterations == its


# -- tests ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("structure", ("full", "diag", "sphere"))
@pytest.mark.parametrize("name", ("l2", "l1", "huber", "cauchy", "gm"))
def test_core_model_matches_reference(structure, name):
    m, K0, b0, x0, _ = problem(structure)
    kernel = make(name)
    got = refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="numpy")
    ref = reference_refine(m, K0, b0, x0, kernel=kernel, structure=structure)
    assert ref[5] > 2  # the problem takes several LM steps (not a trivial comparison)
    assert_same(got, ref)


@pytest.mark.parametrize("structure", ("full", "diag"))
@pytest.mark.parametrize("effect", ("temperature_offset", "temperature_scale", "axis_nonlinearity"))
@pytest.mark.parametrize("name", ("cauchy", "l1"))
def test_effects_match_reference(structure, effect, name):
    """temperature_offset is additive (∂f/∂u = None); the other two have a jac_u."""
    from streamcal.model import build_effects

    m, K0, b0, x0, cov = problem(structure, seed=11)
    effects = build_effects([effect], cov)
    assert (effects[0].jac_u(effects[0].initial(), m, cov) is None) == (effect == "temperature_offset")
    thetas = [0.001 * np.ones(e.n_params()) for e in effects]
    kernel = make(name)
    got = refine(m, K0, b0, x0, kernel=kernel, structure=structure, effects=effects, covariates=cov,
                 thetas=thetas)
    ref = reference_refine(m, K0, b0, x0, kernel=kernel, structure=structure, effects=effects,
                           cov=cov, thetas=thetas)
    assert ref[5] > 2
    assert_same(got, ref)


def test_two_effects_and_damping_retries_match_reference():
    """A far start (large λ retries) with an additive and a u-dependent effect together."""
    from streamcal.model import build_effects

    m, K0, b0, x0, cov = problem("full", seed=7)
    K0 = 1.3 * K0
    effects = build_effects(["temperature_offset", "temperature_scale"], cov)
    kernel = make("gm")
    got = refine(m, K0, b0, x0, kernel=kernel, effects=effects, covariates=cov, lam0=1e-6)
    ref = reference_refine(m, K0, b0, x0, kernel=kernel, effects=effects, cov=cov, lam0=1e-6)
    assert_same(got, ref)


@pytest.mark.parametrize("effect", (None, "temperature_scale"))
def test_blocks_of_samples_match_reference(monkeypatch, effect):
    """Samples processed in several blocks (a short last one too) give the same result."""
    from streamcal.fitting import lm_blocks
    from streamcal.model import build_effects

    monkeypatch.setattr(lm_blocks, "BLOCK", 70)
    m, K0, b0, x0, cov = problem("full", seed=5)
    assert len(m) % lm_blocks.BLOCK and len(m) > 2 * lm_blocks.BLOCK
    effects = build_effects([effect], cov) if effect else ()
    kernel = make("cauchy")
    engine = lm_blocks.NumpyEngine(lm._Model(m, "full", True, effects, cov), m.T.copy(), kernel)
    assert len(engine.slices) > 2            # the refine below does run in several blocks
    got = refine(m, K0, b0, x0, kernel=kernel, effects=effects, covariates=cov, engine="numpy")
    ref = reference_refine(m, K0, b0, x0, kernel=kernel, effects=effects, cov=cov)
    assert_same(got, ref)


def test_inputs_are_not_modified_and_outputs_are_row_major():
    m, K0, b0, x0, _ = problem("full")
    copies = [a.copy() for a in (m, K0, b0, x0)]
    res = refine(m, K0, b0, x0, kernel=make("cauchy"))
    for a, c in zip((m, K0, b0, x0), copies):
        np.testing.assert_array_equal(a, c)
    assert res.x.shape == x0.shape and res.residuals.shape == m.shape
    assert res.x.flags.c_contiguous and res.residuals.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(res.x, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(res.residuals, res.x @ res.K.T + res.b - m, atol=1e-12)


# -- stage 1: the L1 program handed to Clarabel as its dual vs cvxpy's primal ---------------------
@pytest.mark.parametrize("case", ("outliers_30", "one_sided"))
def test_l1_dual_reaches_the_cvxpy_optimum(case):
    from streamcal.fitting import ellipsoid
    from streamcal.fitting.normalize import normalize

    rng = np.random.default_rng(17)
    x = rng.standard_normal((250, 3))
    if case == "one_sided":
        x[:, 2] = np.abs(x[:, 2]) + 0.3
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    K = np.eye(3) + 0.1 * np.triu(rng.standard_normal((3, 3)))
    m = x @ K.T + 0.3 + 0.01 * rng.standard_normal((250, 3))
    if case == "outliers_30":
        m[:75] += rng.uniform(-1.0, 1.0, (75, 3))
    m_n = normalize(m)[0]
    phi = ellipsoid.design_matrix(m_n)

    def vec(C, d, e):
        return np.r_[C[0, 0], C[1, 1], C[2, 2], C[0, 1], C[0, 2], C[1, 2], d, e]

    v_dual = vec(*ellipsoid.fit_l1_ellipsoid(m_n))
    v_cvx = vec(*ellipsoid.L1EllipsoidProblem(len(m_n)).solve(m_n))
    assert abs(v_dual[:3].sum() - 1) < 1e-8                       # feasible: trace C = 1
    assert np.linalg.eigvalsh(ellipsoid.unpack(v_dual)[0])[0] > -1e-8   # and C ⪰ 0
    f_dual, f_cvx = np.abs(phi @ v_dual).sum(), np.abs(phi @ v_cvx).sum()
    assert f_dual <= f_cvx * (1 + 1e-6)
    np.testing.assert_allclose(v_dual, v_cvx, atol=1e-4)


@pytest.mark.skipif(not (os.environ.get("CI") or lm_compiled.available()),
                    reason="the C extension was not built (no C compiler at install); CI builds it")
@pytest.mark.parametrize("structure", ("full", "diag", "sphere"))
@pytest.mark.parametrize("name", ("cauchy", "gm"))
def test_compiled_engine_matches_reference(structure, name):
    """The compiled per-sample loops (streamcal.fitting.lm_compiled) against the literal
    transcription, like the numpy engine above (outliers included: clamped Triggs terms)."""
    m, K0, b0, x0, _ = problem(structure)
    kernel = make(name)
    got = refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="compiled")
    ref = reference_refine(m, K0, b0, x0, kernel=kernel, structure=structure)
    assert ref[5] > 2
    assert_same(got, ref)


def test_tangent_basis_is_orthonormal_and_perpendicular():
    """T (3,2,N) at unit x: TᵀT = I and Tᵀx = 0, at the poles and across z = ±0 included."""
    from streamcal.fitting.lm_blocks import _tangent_basis

    rng = np.random.default_rng(3)
    x = rng.standard_normal((3, 500))
    x[:, :6] = [[0, 0, 1, 1, 0, 1e-9], [0, 0, 0, 0, 1, 1], [1, -1, 0.0, -0.0, 0, 1e-12]]
    x /= np.linalg.norm(x, axis=0)
    T = _tangent_basis(x)
    gram = np.einsum("aik,ajk->ijk", T, T)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(2)[:, :, None], gram.shape), atol=1e-14)
    np.testing.assert_allclose(np.einsum("aik,ak->ik", T, x), 0.0, atol=1e-14)


@pytest.mark.parametrize("beta", (0.5, 4.0))
def test_the_gauge_weight_does_not_change_the_step(beta):
    """The literal 3×3 algebra at another β reaches what the tangent-plane engine reaches: the
    step has no component along x_j, so β (the gauge) drops out."""
    m, K0, b0, x0, _ = problem("full", seed=7)
    got = refine(m, K0, b0, x0, kernel=make("cauchy"), engine="numpy")
    ref = reference_refine(m, K0, b0, x0, kernel=make("cauchy"), beta=beta)
    assert_same(got, ref)
