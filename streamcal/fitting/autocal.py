"""The two-stage robust autocalibration (paper §II): normalize → L1 ellipsoid (Algorithm 1) →
robust LM over the model and the directions (Algorithm 2) → canonical form → sensor units.

Where we depart from the paper, on purpose:

- Kernel width from the data. The paper fixes τ = √3 (optimal for σ = 1 in its units) and loses
  accuracy when the noise is larger (its Fig. 5). By default we estimate the noise σ̂ robustly
  from the residuals and set τ = c·σ̂ with c the kernel's 95 %-Gaussian-efficiency constant
  (Cauchy 2.385, Huber 1.345, Geman–McClure 3.787); re-estimating σ̂ from the refined residuals
  (trimmed at 3τ) until it settles. ``tau=<number>`` (sensor units) restores a fixed width.
- Graduated robustness (``kernel="auto"``, the default): Cauchy to convergence — convex near
  the optimum, so it finds the right basin from the L1 start — then a Geman–McClure polish
  (τ = 3.787σ̂), whose redescending influence ignores the outliers that land near the ellipsoid
  and act as extra noise on Cauchy. On the paper's protocol this keeps autocal within 5 % of
  the oracle that knows the inliers, up to σ = 2 and 30 % outliers (``RESULTS.md``).
- A coherent disturbance (a magnet riding on the board for a while): the LM runs on the
  undisturbed support, then one shape K with offsets b and b + Δ is refitted on every sample
  (``shared_shape``) and kept when both shells fit it alike; the calibration is (K, b).
- Stage 1 on a bounded, well-spread subset (``stage1_max`` samples): the L1 program costs
  O(N) interior-point work per call while stage 2 refines every sample anyway. The default
  fit's clean algebraic start is tried first on every sample (up to ``CLEAN_START_ROWS``): its
  contamination check is then the one the robust path needs anyway, and the subset is drawn
  only when the data look contaminated.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from ..constants import HALF_NORMAL_MEDIAN, OUTLIER_WIDTHS
from ..errors import InsufficientDataError
from .ellipsoid import (directions_and_residuals, directions_from_model, ellipsoid_to_model,
                        fit_l1_ellipsoid, fit_l2_ellipsoid, spread_subset)
from .kernels import EFFICIENCY_TAU, WIDTH_KERNELS, make_kernel
from .lm import LMResult, refine
from .mixture_polish import mixture_polish
from .normalize import normalize
from .observability import assess
from .order_stats import quantile, quantiles, sorted_median
from .robust_start import KEEP, coherent_start, lqs_score, radial_error, robust_start
from .shared_shape import INDICATOR, DisturbanceShift, consistent, shift_start

#: A sample is an outlier when its residual exceeds this many kernel widths.
#: Median over lower-quartile ratio of the stage-1 residuals above which the L1 start is
#: double-checked by :func:`robust_start` (|N(0,1)| gives 0.674 / 0.319 = 2.1).
CONTAMINATION_RATIO = 3.0
#: ... or when even the nearest quarter of samples sits this far (relative) from the surface.
RELATIVE_LIMIT = 0.01
#: Quantile of |N(0,1)| at KEEP (0.25): σ from the nearest quarter of radial residuals.
HALF_NORMAL_QUANTILE_KEEP = 0.31863936396437514
#: Under a coherent disturbance the LM runs on the start's supporting chunks, less the samples
#: farther than this many start bands from the start's surface.
SUPPORT_BANDS = 2.0
#: The shared-shape refinement is first checked on about this many samples (time-strided).
SHARED_SHAPE_CHECK = 3000
#: Initial LM damping of the default fit's first (loose) Cauchy pass from a clean algebraic
#: start (else refine's 10): the start is near the optimum, so heavily damped first steps only
#: cost iterations.
CLEAN_LAM0 = 1.0
#: When not one residual of the clean algebraic start lies beyond 2 Cauchy widths of its σ̂
#: (OUTLIER_WIDTHS × 2.385 σ̂ ≈ 4.8 σ̂), the Cauchy pass is this many LM steps from damping
#: OUTLIER_FREE_LAM0: on such data it only moves the start off the algebraic fit's bias, so that
#: σ̂ and the Geman–McClure polish start near the optimum; the polish then converges to rtol as
#: before. The pass's second step had lowered the cost by about 2e-5 relative (freeimucal
#: N = 1000, paper protocol σ = 0.5–2). On the 75 clean paper-protocol trials: 3 LM iterations
#: in 71 fits (was 4–6), the calibration within 1.2e-5 (eq. 40) of the full pass. A few gross
#: outliers (1 % of the paper protocol: 5–17 beyond the gate at every seed) keep the full pass:
#: there a single step moved the calibration by up to 3.1e-4. On large real recordings the gate
#: closes more often (a heavier tail than Gaussian), which keeps the full pass there.
OUTLIER_FREE_STEPS, OUTLIER_FREE_LAM0 = 1, 0.01
#: The Geman–McClure polish starts at the damping the Cauchy pass ended at, within
#: [POLISH_LAM_MIN, refine's default 10]: it starts at that pass's optimum, where λ0 = 10 only
#: shortens the first steps (on clean data the polish then stopped one damped step short of its
#: optimum); a pass that ended stalled (λ raised on every refused trial) starts it at 10 as before.
POLISH_LAM_MIN, POLISH_LAM_MAX = 1e-3, 10.0
#: Up to this many samples the default fit's clean algebraic start is the L2 ellipsoid of every
#: sample (a (10,N) design matrix, 1.6 MB at the cap); above it, of the stage-1 spread subset as
#: before, which bounds the weight of a long dwell in one orientation (long streamed or logged
#: recordings). The bound is on behaviour, not cost: the start with its check costs 2.3 ms at
#: 20 000 paper-protocol samples against 10.3 ms by the subset (12 vs 53 ms at 1e5).
CLEAN_START_ROWS = 20_000


@dataclass
class AutocalResult:
    """Everything the pipeline learnt, in sensor units unless named ``_n`` (normalized)."""

    K: np.ndarray
    b: np.ndarray
    x: np.ndarray             # (N,3) directions, canonical frame
    thetas: list              # per effect, normalized units
    residuals: np.ndarray     # (N,3) sensor units
    residual_norms: np.ndarray  # (N,) ‖residuals_j‖, sensor units
    weights: np.ndarray       # (N,) robust weights ρ′
    inliers: np.ndarray       # (N,) bool
    sigma: float              # robust noise estimate, sensor units
    tau: float | None         # kernel width used, sensor units
    scale: float              # normalization scale
    center: np.ndarray
    lm: LMResult
    #: the last LM run that moved the parameters (``lm`` may be a final evaluation on every
    #: sample): its status, iterations and message
    solver: LMResult | None = None

    @property
    def rms(self) -> float:
        """Sensor estimation error over inliers (eq. 41), sensor units."""
        r = self.residuals[self.inliers]
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def robust_sigma(r_norm: np.ndarray) -> float:
    """σ from residual norms, assuming they are |N(0, σ²)| (radial) for inliers."""
    return float(np.median(r_norm) / HALF_NORMAL_MEDIAN)


#: Truncation (in σ) of the fixed-point noise estimate, and the median of |N(0,1)| below it:
#: Φ⁻¹(½ + ¼(2Φ(2.5) − 1)).
TRUNCATION, TRUNCATED_MEDIAN = 2.5, 0.6649605


def truncated_sigma(r_norm: np.ndarray, sigma: float, iters: int = 60) -> float:
    """Fixed point of σ = median(|r| < 2.5σ) / 0.665, iterated from ``sigma``.

    Unbiased for Gaussian residuals; outliers count only while they fall inside the window,
    so an overestimate shrinks step by step even when most samples are outliers."""
    # one sort, then every window is a prefix whose median is read off (a third of the cost of
    # order_stats.median on each window at N = 1000 to 1e5, the same numbers)
    ordered = np.sort(r_norm)
    for _ in range(iters):
        k = int(np.searchsorted(ordered, TRUNCATION * sigma, side="left"))
        if k < 10:
            break
        new = max(sorted_median(ordered, k) / TRUNCATED_MEDIAN, 1e-9)
        converged = abs(new - sigma) <= 0.005 * sigma
        sigma = new
        if converged:
            break
    return sigma


def fit_sigma(r_norm: np.ndarray) -> float:
    """σ̂ of residual norms ``r_norm`` (N,): :func:`truncated_sigma` started from the nearest
    quarter of them (unbiased for Gaussian noise, far less inflated than the median when many
    samples are outliers)."""
    return truncated_sigma(r_norm, max(quantile(r_norm, KEEP) / HALF_NORMAL_QUANTILE_KEEP, 1e-9))


def _looks_contaminated(r: np.ndarray, relative: np.ndarray) -> bool:
    """Stage-1 residuals r (N,) skewed by outliers, or even their nearest quarter more than
    RELATIVE_LIMIT of the field away (``relative``: radial errors as a fraction of the field)."""
    q25, q50 = quantiles(r, (KEEP, 0.5))
    return bool(q50 > CONTAMINATION_RATIO * max(q25, 1e-300)
                or quantile(relative, KEEP) > RELATIVE_LIMIT)


def _clean_l2_start(m_n: np.ndarray):
    """(K, b, x, r) of the algebraic L2 ellipsoid of the samples m_n (N,3) — directions x
    (N,3) and residual norms r (N,) at it — when its residuals show no outliers
    (:func:`_looks_contaminated`), else None. On clean data the L1 fit (a conic program, ~50×
    the cost) only gives the LM another start near the same optimum."""
    try:
        K, b = ellipsoid_to_model(*fit_l2_ellipsoid(m_n))
    except InsufficientDataError:
        return None
    if not (np.isfinite(K).all() and np.isfinite(b).all()):
        return None
    x, r, relative = directions_and_residuals(K, b, m_n)
    return None if _looks_contaminated(r, relative) else (K, b, x, r)


def _shaped(K: np.ndarray, b: np.ndarray, structure: str, fit_b: bool):
    """(K, b) restricted to the model's structure (``full``, ``diag``, ``sphere``) and offset."""
    if not fit_b:
        b = np.zeros(3)
    if structure == "diag":
        K = np.diag(np.linalg.norm(K, axis=1))
    elif structure == "sphere":
        K = np.eye(3) * float(np.prod(np.diag(K)) ** (1 / 3))
    return K, b


def stage1(m_n: np.ndarray, structure: str = "full", fit_b: bool = True, method: str = "l1",
           stage1_max: int = 300, clean_start: bool = False):
    """Initial (K, b) in normalized units from an ellipsoid fit on a well-spread subset.
    ``clean_start``: with ``method="l1"``, the algebraic L2 fit when its residuals show no
    outliers (:func:`_clean_l2_start`), the L1 fit only when they do."""
    subset = m_n[spread_subset(m_n, stage1_max)]
    start = _clean_l2_start(subset) if method == "l1" and clean_start else None
    try:
        K, b = start[:2] if start else ellipsoid_to_model(*(fit_l1_ellipsoid if method == "l1" else fit_l2_ellipsoid)(subset))
    except InsufficientDataError:
        if method != "l1":
            raise
        # One-sided data can push the L1 quadric onto the PSD boundary (a cylinder); the L2
        # quadric usually remains an ellipsoid and is a fair start for the robust LM.
        K, b = ellipsoid_to_model(*fit_l2_ellipsoid(subset))
    return _shaped(K, b, structure, fit_b)


#: The default kernel: Cauchy, then a Geman–McClure polish.
AUTO = "auto"


def autocal(m: np.ndarray, *, kernel: str = AUTO, tau: float | str | None = None,
            structure: str = "full", fit_b: bool = True, effects: Sequence = (),
            covariates: Mapping[str, np.ndarray] | None = None, stage1_method: str = "l1",
            stage1_max: int = 300, max_iter: int = 300, rtol: float = 1e-6,
            max_width_rounds: int = 4, check_coverage: bool = False,
            initial: tuple[np.ndarray, np.ndarray] | None = None) -> AutocalResult:
    """Run both stages on measurements ``m`` (N,3) in the sensor unit.

    ``tau``: None → from the data (see module doc); ``"paper"`` → √3 sensor units; a number →
    that width in sensor units. Effects (``streamcal.model`` objects) are fitted jointly.
    ``check_coverage``: when stage 1 finds no ellipsoid, say whether the coverage is to blame.
    (Coverage of the refined fit is judged by the caller, on its inliers: stage-1 directions
    can be distorted by outliers.)
    ``initial``: (K, b) in sensor units to start the LM from instead of stage 1 (warm start).
    """
    polish = kernel == AUTO
    if polish:
        kernel = "cauchy"
    m = np.asarray(m, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"measurements must have shape (N,3), got {m.shape}")
    m_n, center, scale = normalize(m)
    # the default fit's kernels (Cauchy, GM) start from a clean algebraic fit: same optimum,
    # ~50x cheaper than the L1 conic program; tried first on every sample (CLEAN_START_ROWS)
    clean_start = kernel in ("cauchy", "gm") and stage1_method == "l1"
    start = None
    if initial is None and clean_start and len(m_n) <= CLEAN_START_ROWS:
        start = _clean_l2_start(m_n)
    try:
        if initial is not None:
            K0, b0 = np.asarray(initial[0]) / scale, (np.asarray(initial[1]) - center) / scale
        elif start is not None:
            K0, b0 = _shaped(start[0], start[1], structure, fit_b)
        else:
            K0, b0 = stage1(m_n, structure, fit_b, stage1_method, stage1_max,
                            clean_start=clean_start)
    except InsufficientDataError:
        if check_coverage:  # a degenerate ellipsoid is most often a coverage problem: say which
            seen = assess(m_n / np.linalg.norm(m_n, axis=1, keepdims=True), structure, fit_b, m=m_n)
            if not seen.ok:
                raise InsufficientDataError(seen.message) from None
        raise
    # support: the samples of the time chunks that agree with the start when a coherent
    # disturbance (a second shell, contiguous in time) was found; None otherwise
    support = None
    if start is not None and structure == "full" and fit_b:
        # the start is the checked fit itself: its directions, residuals and verdict stand
        x0, r0, clean = start[2], start[3], True
    else:
        x0 = directions_from_model(K0, b0, m_n)
        r0 = np.linalg.norm(x0 @ K0.T + b0 - m_n, axis=1)
        clean = initial is None and not _looks_contaminated(r0, radial_error(K0, b0, m_n))
    if initial is None and not clean:
        K1, b1 = robust_start(K0, b0, m_n)
        spread = m_n[spread_subset(m_n, 2000)]
        if lqs_score(K1, b1, spread) < lqs_score(K0, b0, spread):
            K0, b0 = K1, b1
        coherent = coherent_start(K0, b0, m_n) if structure == "full" and fit_b else None
        if coherent is not None:
            # the chunk support less the samples far off the start's shell: a chunk on the edge
            # of the disturbance holds disturbed samples, and on a cap a few of them are enough
            # to drag the fit towards the disturbed shell
            near = radial_error(coherent.K, coherent.b, m_n) < SUPPORT_BANDS * coherent.band
            K0, b0, support = coherent.K, coherent.b, coherent.support & near
            span = ~coherent.support
        x0 = directions_from_model(K0, b0, m_n)
        r0 = np.linalg.norm(x0 @ K0.T + b0 - m_n, axis=1)
    # σ from the nearest quarter of residuals: unbiased for Gaussian noise and far less
    # inflated than the median when many samples are outliers
    sigma_n = fit_sigma(r0)

    def width(sig):
        if kernel not in WIDTH_KERNELS:
            return None
        if tau is None:
            return EFFICIENCY_TAU[kernel] * sig
        if tau == "paper":
            return np.sqrt(3.0) / scale
        return float(tau) / scale

    def solve(m_n, covariates, K_start, b_start, x_start, sigma_start, effects=effects, thetas=None,
              outlier_free=False):
        """Width rounds, then the polish, on samples m_n (with their covariates, effects and
        starting effect parameters): returns (LMResult, σ̂, τ) in normalized units.
        ``outlier_free``: the clean start shows no outlier (OUTLIER_FREE_STEPS)."""
        sig = sigma_start
        tau_cur = width(sig)
        adaptive = tau is None and tau_cur is not None
        # While the width is still being estimated a loose tolerance suffices: the final pass
        # (same or re-estimated width) polishes to rtol from a nearby start.
        from_clean = clean and polish and adaptive
        one_step = from_clean and outlier_free
        res = refine(m_n, K_start, b_start, x_start, kernel=make_kernel(kernel, tau_cur),
                     structure=structure, fit_b=fit_b, effects=effects, covariates=covariates,
                     thetas=thetas, max_iter=min(max_iter, OUTLIER_FREE_STEPS) if one_step
                     else max_iter, rtol=max(rtol, 1e-3) if adaptive else rtol,
                     lam0=OUTLIER_FREE_LAM0 if one_step else CLEAN_LAM0 if from_clean else 10.0)
        polished = not adaptive
        for _ in range(max_width_rounds if adaptive else 0):
            new_sig = truncated_sigma(res.residual_norms, sig)
            settled = abs(new_sig - sig) <= 0.05 * sig
            sig, tau_cur = new_sig, width(new_sig)
            if settled and polish and clean:
                # clean data: the Cauchy pass at the settled width would only move the start
                # of the Geman–McClure polish (whose width σ̂ now fixes), not its optimum
                polished = True
                break
            res = refine(m_n, res.K, res.b, res.x, kernel=make_kernel(kernel, tau_cur),
                         structure=structure, fit_b=fit_b, effects=effects, covariates=covariates,
                         thetas=res.thetas, max_iter=max_iter,
                         rtol=rtol if settled else max(rtol, 1e-3))
            polished = settled
            if settled:
                break
        if not polished:
            res = refine(m_n, res.K, res.b, res.x, kernel=make_kernel(kernel, tau_cur),
                         structure=structure, fit_b=fit_b, effects=effects, covariates=covariates,
                         thetas=res.thetas, max_iter=max_iter, rtol=rtol)
        if polish:
            tau_cur = EFFICIENCY_TAU["gm"] * sig
            res = refine(m_n, res.K, res.b, res.x, kernel=make_kernel("gm", tau_cur),
                         structure=structure, fit_b=fit_b, effects=effects, covariates=covariates,
                         thetas=res.thetas, max_iter=max_iter, rtol=rtol,
                         lam0=min(max(res.lam, POLISH_LAM_MIN), POLISH_LAM_MAX))
        return res, sig, tau_cur

    def _shared_shape(part, sigma_part, span, support, x_part):
        """One shape K, two offsets (b on the support, b + Δ on the disturbed ``span``) fitted
        on every sample from the support fit ``part``; Δ starts at the span's offset with the
        part's K fixed. Returns (LMResult without the shift term, σ̂, τ, the samples not in the
        span) when both shells fit it alike, else None (the support fit stands)."""
        if span.sum() < 10 or (~span).sum() < 10:
            return None
        delta = shift_start(part.K, part.b, m_n[span])
        x_start = x_part.copy()
        x_start[span] = directions_from_model(part.K, part.b + delta, m_n[span])
        cov = {**(covariates or {}), INDICATOR: span.astype(float)}
        shift_effects = [*effects, DisturbanceShift()]
        K_s, b_s, th_s = part.K, part.b, [*part.thetas, delta]
        # first on every SHARED_SHAPE_STRIDE-th sample (time order keeps both spans' shares):
        # a disturbance that is not a pure shift is rejected at a fraction of the full cost
        stride = max(1, len(m_n) // SHARED_SHAPE_CHECK)
        r_part = np.full(len(m_n), np.nan)          # the support fit's residual norms
        r_part[support] = part.residual_norms
        for rows in ([slice(None, None, stride)] if stride > 1 else []) + [slice(None)]:
            joint, sig, tau_j = solve(m_n[rows], {k: np.asarray(v)[rows] for k, v in cov.items()},
                                      K_s, b_s, x_start[rows], sigma_part,
                                      effects=shift_effects, thetas=th_s)
            rn = joint.residual_norms
            limit = OUTLIER_WIDTHS * (tau_j if tau_j is not None else 2.0 * sig)
            if not consistent(rn, span[rows], limit, support[rows], r_part[rows]):
                return None
            K_s, b_s, th_s, sigma_part = joint.K, joint.b, joint.thetas, sig
        joint.thetas = joint.thetas[:-1]
        return joint, sig, tau_j, ~span

    if support is None:
        outlier_free = clean and float(np.max(r0)) <= OUTLIER_WIDTHS * EFFICIENCY_TAU["cauchy"] * sigma_n
        result, sigma_n, tau_n = solve(m_n, covariates, K0, b0, x0, sigma_n, outlier_free=outlier_free)
        if polish and tau is None:  # outliers near the shell: their ML fit (a no-op without)
            result, _ = mixture_polish(result, sigma_n, lambda res, k: refine(
                m_n, res.K, res.b, res.x, kernel=k, structure=structure, fit_b=fit_b,
                effects=effects, covariates=covariates, thetas=res.thetas, max_iter=max_iter,
                rtol=rtol))
        solver = result
    else:
        # A coherent disturbance: refine on the undisturbed chunks only (the disturbed shell
        # would drag a cap-limited fit towards it), then evaluate every sample at that model.
        cov_support = {k: np.asarray(v)[support] for k, v in (covariates or {}).items()}
        result, sigma_n, tau_n = solve(m_n[support], cov_support, K0, b0, x0[support], sigma_n)
        x_all = directions_from_model(result.K, result.b, m_n)
        x_all[support] = result.x
        shared = _shared_shape(result, sigma_n, span, support, x_all)
        if shared is not None:
            result, sigma_n, tau_n, keep = shared
            x_all = directions_from_model(result.K, result.b, m_n)
            x_all[keep] = result.x[keep]
        solver = result
        result = refine(m_n, result.K, result.b, x_all,
                        kernel=make_kernel("gm" if polish else kernel, tau_n),
                        structure=structure, fit_b=fit_b, effects=effects, covariates=covariates,
                        thetas=result.thetas, max_iter=0)
    if not np.isfinite(result.K).all() or (np.abs(np.diag(result.K)) < 1e-9).any():
        raise InsufficientDataError("the refinement diverged: the data do not determine the model")
    # canonical form: positive diagonal (flip the matching direction components)
    signs = np.sign(np.diag(result.K))
    signs[signs == 0] = 1
    K_n = result.K * signs[None, :]
    x = result.x * signs[None, :]
    rn = result.residual_norms
    if tau_n is not None:
        inliers = rn <= OUTLIER_WIDTHS * tau_n
    else:
        inliers = rn <= max(4.0 * sigma_n, 1e-12) if kernel != "l2" else np.ones(len(rn), bool)
        inliers |= kernel == "l2"
    return AutocalResult(K=scale * K_n, b=scale * result.b + center, x=x, thetas=result.thetas,
                         residuals=scale * result.residuals, residual_norms=scale * rn,
                         weights=result.weights, inliers=inliers,
                         sigma=scale * sigma_n, tau=None if tau_n is None else scale * tau_n,
                         scale=scale, center=center, lm=result, solver=solver)
