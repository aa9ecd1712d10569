"""A last step for contaminated data: the maximum-likelihood fit under Gaussian inliers plus a
locally flat density of outliers (``autocal`` runs it after the Geman–McClure polish, only when
its stage-1 diagnostics flagged outliers).

Why: outliers displaced by about a field radius (the paper's protocol, ζ = 100) land near the
shell too. Near the surface their density is flat, so under ANY kernel centred on the current
fit they add variance (∫ψ² times their density) but no stiffness (∫ψ′ = 0 over a flat density).
The kernel that minimizes that loss is the mixture's score,

    ρ′(s) = w(s) = e / (e + κ),   e = exp(−s / 2σ²),   κ = f₀ σ √(2π) / n_in,

the posterior probability that a sample with squared residual s is an inlier (f₀: outliers per
unit of signed normal residual near the shell; n_in: inliers). At the paper's σ = 1, 30 %
outliers (about 10 outliers within ±3σ of the shell, 700 inliers), the asymptotic error of a
location fit over the inlier-only fit is 1.051× for GM at τ = 3.787σ (the polish), 1.038× for
the best hard rejection (at 3σ) and 1.030× for this kernel (numerical integration of
E[ψ²]/E[ψ′]²; ``tools/bench_contamination.py`` measures the full fit).

σ, f₀ and n_in come from the residual norms by EM on a half-normal + uniform mixture over
[0, WINDOW·σ̂] — σ from the weighted second moment, not a truncated median that the near-shell
outliers inflate.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

#: The EM mixture is fitted on residual norms below this many σ̂ (the uniform part's support).
WINDOW = 10.0
#: EM iterations at most, and the relative change of σ that stops them.
EM_ITERS, EM_TOL = 200, 1e-6
#: Refits (EM, then LM at the new σ, κ) at most, and the relative σ change that stops them.
ROUNDS, ROUND_TOL = 3, 0.01
#: The step runs only when at least this share of residual norms lies beyond TAIL σ̂ (Gaussian:
#: 6·10⁻⁵): clean data and a few gross outliers keep the Geman–McClure fit as it was.
TAIL, SHARE = 4.0, 0.05
#: The step is skipped when EM moves σ beyond this factor of the starting σ̂ either way, or
#: finds fewer inliers than MIN_INLIERS: the mixture model does not describe the residuals.
SIGMA_FACTOR, MIN_INLIERS = 1.5, 20


@dataclass(frozen=True)
class GaussUniform:
    """ρ(s) = −2σ²(1 + κ) log((e + κ)/(1 + κ)), e = exp(−s/2σ²): negative log-likelihood (up to
    scale and constant) of a Gaussian inlier of width σ (unit of the residual) against a flat
    outlier density κ relative to the Gaussian's peak. ρ′(0) = 1, ρ′ → 0 far out."""

    sigma: float
    kappa: float
    name = "gauss_uniform"

    def evaluate(self, s):
        s = np.asarray(s, dtype=float)
        v = 2.0 * self.sigma * self.sigma
        e = np.exp(-s / v)
        q = e + self.kappa
        c = 1.0 + self.kappa
        return (-v * c * np.log(q / c), c * e / q, -c * e * self.kappa / (v * q * q))

    def rho(self, s):
        v = 2.0 * self.sigma * self.sigma
        c = 1.0 + self.kappa
        return -v * c * np.log((np.exp(-np.asarray(s, dtype=float) / v) + self.kappa) / c)


def mixture_fit(r_norm: np.ndarray, sigma: float) -> tuple[float, float, float] | None:
    """EM for residual norms ``r_norm`` (N,) ~ p·|N(0, σ²)| + (1 − p)·U(0, L), L = WINDOW·σ
    (σ the starting estimate, kept fixed for L). Returns (σ, κ, n_in) or None when the fit is
    implausible (σ beyond SIGMA_FACTOR of the start, fewer than MIN_INLIERS inliers, no
    outliers at all in the window)."""
    L = WINDOW * sigma
    r = r_norm[r_norm < L]
    if len(r) < MIN_INLIERS:
        return None
    r2 = r * r
    sig, p = sigma, 0.9
    for _ in range(EM_ITERS):
        g = p * np.sqrt(2.0 / np.pi) / sig * np.exp(-r2 / (2.0 * sig * sig))
        w = g / (g + (1.0 - p) / L)
        p = float(np.clip(w.mean(), 1e-6, 1 - 1e-6))
        new = float(np.sqrt(np.sum(w * r2) / max(np.sum(w), 1e-300)))
        done = abs(new - sig) <= EM_TOL * sig
        sig = new
        if done:
            break
    n_in = p * len(r)
    f0 = (1.0 - p) * len(r) / L / 2.0       # outliers per unit of signed residual
    if not (sigma / SIGMA_FACTOR <= sig <= sigma * SIGMA_FACTOR) or n_in < MIN_INLIERS or f0 <= 0:
        return None
    return sig, f0 * sig * np.sqrt(2.0 * np.pi) / n_in, n_in


def heavy_tail(r_norm: np.ndarray, sigma: float) -> bool:
    """At least SHARE of the residual norms (N,) lie beyond TAIL·σ: the outliers are many."""
    return bool(np.mean(r_norm > TAIL * sigma) >= SHARE)


def mixture_polish(result, sigma: float, refine_with: Callable):
    """Refit ``result`` (an LMResult, normalized units) with :class:`GaussUniform`, σ and κ by
    :func:`mixture_fit` on its residual norms, repeated while σ moves more than ROUND_TOL.

    ``refine_with(result, kernel)`` runs the LM from ``result`` with ``kernel`` (the caller's
    samples, structure and effects). Returns ``(LMResult, σ)``: the input unchanged when the
    mixture model does not describe the residuals (:func:`mixture_fit` returns None) or fewer
    than SHARE of them lie beyond TAIL σ (:func:`heavy_tail`)."""
    r_norm = result.residual_norms
    if not heavy_tail(r_norm, sigma):
        return result, sigma
    for round_ in range(ROUNDS):
        if round_:
            r_norm = result.residual_norms
        found = mixture_fit(r_norm, sigma)
        if found is None:
            break
        new_sigma, kappa, _ = found
        result = refine_with(result, GaussUniform(new_sigma, kappa))
        settled = abs(new_sigma - sigma) <= ROUND_TOL * sigma
        sigma = new_sigma
        if settled:
            break
    return result, sigma
