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

The per-sample algebra lives in :mod:`streamcal.fitting.lm_blocks` (numpy, every model) and
:mod:`streamcal.fitting.lm_compiled` (C, the core model under the default fit's kernels).
``tests/test_lm_equivalence.py`` checks the result against a literal transcription of steps 1–5.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from . import lm_compiled
from .kernels import L2, Cauchy, GemanMcClure
from .lm_blocks import K_ENTRIES, NumpyEngine

LAMBDA_MIN, LAMBDA_MAX = 1e-14, 1e14


@dataclass
class LMResult:
    """Outcome of :func:`refine`. Units are those of ``m`` (normalized in the pipeline)."""

    K: np.ndarray            # (3,3) upper triangular
    b: np.ndarray            # (3,)
    x: np.ndarray            # (N,3) unit directions
    thetas: list             # per effect, (P_e,) arrays
    residuals: np.ndarray    # (N,3) r_j at the solution
    residual_norms: np.ndarray  # (N,) ‖r_j‖, from the engine's own ‖r_j‖² (no second pass)
    weights: np.ndarray      # (N,) ρ′(s_j) — 1 for inliers, → 0 for outliers
    cost: float
    iterations: int
    converged: bool
    #: the damping λ the run ended with (lowered after its last accepted step, or raised after
    #: its last refused trial): where a follow-on run from this solution may start
    lam: float
    history: list = field(default_factory=list)
    #: :data:`streamcal.fitting.damped_lm.STATUSES`: ``converged`` (relative decrease below
    #: rtol), ``stalled`` (no trial step lowered the cost; ``converged`` is also True then, as
    #: it always was) or ``max_iter``; ``message`` in words.
    status: str = "max_iter"
    message: str = ""


#: Flat positions in a 3×3 K of each structure's free entries (K = kI puts k on the diagonal).
_K_FLAT = {name: np.array([3 * i + j for i, j in entries]) for name, entries in K_ENTRIES.items()}
_K_FLAT["sphere"] = np.array([0, 4, 8])


def _k_vector(K: np.ndarray, structure: str) -> np.ndarray:
    return np.asarray(K, dtype=float).reshape(9)[_K_FLAT[structure][:len(K_ENTRIES[structure])]]


def _k_matrix(k: np.ndarray, structure: str) -> np.ndarray:
    K = np.zeros(9)
    K[_K_FLAT[structure]] = k
    return K.reshape(3, 3)


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



#: A failed step that raises the cost by at most this fraction is rounding at the optimum.
FLAT = 1e-9


def refine(m: np.ndarray, K: np.ndarray, b: np.ndarray, x: np.ndarray, *, kernel=None,
           structure: str = "full", fit_b: bool = True, effects: Sequence = (),
           covariates: Mapping[str, np.ndarray] | None = None, thetas: Sequence | None = None,
           max_iter: int = 300, rtol: float = 1e-6, lam0: float = 10.0, max_trials: int = 12,
           engine: str = "auto") -> LMResult:
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
        engine: ``"numpy"``, ``"compiled"`` (:mod:`streamcal.fitting.lm_compiled`: the core
            model under Cauchy or Geman–McClure, where the C extension was built) or ``"auto"``:
            as :data:`ENGINE_ENV` says (by default compiled where it applies, numpy elsewhere).
            Both give the same result to rounding (not to the last bit).
    """
    kernel = kernel or L2()
    m = np.asarray(m, dtype=float)
    cov = covariates or {}
    model = _Model(m, structure, fit_b, effects, cov)
    K = _k_matrix(_k_vector(np.asarray(K, dtype=float), structure), structure)
    b = np.asarray(b, dtype=float).copy()
    thetas = [np.asarray(t, dtype=float).copy() for t in (thetas or [e.initial() for e in model.effects])]
    # structure of arrays: samples along the last axis
    m_t = np.ascontiguousarray(m.T)
    x = np.array(np.asarray(x, dtype=float).T, order="C")
    engine = _engine(model, m_t, kernel, engine)
    f, state = engine.cost(K, b, thetas, x)
    early = isinstance(kernel, (Cauchy, GemanMcClure))
    lam = lam0
    history = [f]
    converged = False
    iterations = 0
    status = "max_iter"
    for iterations in range(1, max_iter + 1):
        engine.linearize(K, b, thetas, x, state)
        improved = False
        for _ in range(max_trials):
            S, rhs = engine.reduce(lam)
            try:
                dp = engine.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam = min(10 * lam, LAMBDA_MAX)
                continue
            x_new = engine.step(x, dp)
            dk, db, dth = model.split(dp)
            K_new = K + _k_matrix(dk, structure)
            b_new = b + db if fit_b else b
            th_new = [t + d for t, d in zip(thetas, dth)]
            f_new, state_new = engine.cost(K_new, b_new, th_new, x_new)
            if math.isfinite(f_new) and f_new < f:
                improved = True
                rel = (f - f_new) / max(f, 1e-300)
                K, b, thetas, x, f, state = K_new, b_new, th_new, x_new, f_new, state_new
                lam = max(lam / 10, LAMBDA_MIN)
                break
            if early and math.isfinite(f_new) and f_new - f <= FLAT * f:
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
    r, norms, weights = engine.final(K, b, thetas, x, state)
    return LMResult(K=K, b=b, x=np.ascontiguousarray(x.T), thetas=thetas, residuals=r,
                    residual_norms=norms, weights=weights, cost=f,
                    iterations=iterations, converged=converged, history=history, status=status,
                    message={"stalled": f"no step lowered the cost in {max_trials} trials",
                             "converged": f"relative cost decrease below {rtol:g}",
                             "max_iter": f"{max_iter} iterations used"}[status], lam=lam)


#: Environment variable choosing the LM engine of the whole process: unset, the compiled engine
#: (:mod:`streamcal.fitting.lm_compiled`) wherever it applies and numpy elsewhere; ``numpy``,
#: numpy everywhere; ``compiled``, as unset but with a warning when the extension was not built.
#: One choice per environment, never per call history: a batch on worker processes and a serial
#: run in the same environment give the same numbers to the last bit.
ENGINE_ENV = "STREAMCAL_LM_ENGINE"
ENGINES = ("numpy", "compiled")
_warned_not_built = False


def _engine(model, m_t, kernel, name):
    global _warned_not_built
    explicit = name != "auto"
    if not explicit:
        name = os.environ.get(ENGINE_ENV, "").strip().lower() or "auto"
        if name not in ENGINES + ("auto",):
            raise ValueError(f"{ENGINE_ENV}={os.environ[ENGINE_ENV]!r}: choose auto, numpy or compiled")
    elif name not in ENGINES:
        raise ValueError(f"unknown LM engine {name!r}; choose auto, numpy or compiled")
    if name != "numpy":
        reason = lm_compiled.why_not(model, kernel)
        if not reason:
            return lm_compiled.CompiledEngine(model, m_t, kernel)
        if explicit:
            raise ValueError(f"the compiled LM engine does not apply here: {reason}")
        if name == "compiled" and not lm_compiled.BUILT and not _warned_not_built:
            _warned_not_built = True
            warnings.warn(f"{ENGINE_ENV}=compiled but {reason}: the numpy engine runs",
                          RuntimeWarning, stacklevel=3)
    return NumpyEngine(model, m_t, kernel)


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
