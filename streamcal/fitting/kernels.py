"""Robust kernels ρ(s) of the squared residual norm s = ‖r‖² (paper eq. 9–12).

Each kernel is a small immutable object whose ``evaluate(s)`` returns ρ, ρ′, ρ″ at once
(vectorized over samples), as in scipy's ``_lsq/least_squares.py`` loss functions and Ceres'
``LossFunction``; ``rho(s)`` returns ρ alone (the same numbers as ``evaluate(s)[0]``, for the
LM's trial-step cost) and, for the default fit's kernels, ``derivatives(s)`` ρ′ and ρ″
alone (equal to ``evaluate(s)[1:]`` to rounding, for the LM's linearization;
:func:`derivatives_of` falls back to ``evaluate`` for the others). Robustness is applied by
rescaling residuals and Jacobians (Triggs correction, :func:`triggs_correction`), so the LM never
knows which kernel it runs.

The width τ is in the unit of the residual (the LM passes the normalized width).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import HALF_NORMAL_MEDIAN  # noqa: F401  (re-exported)

#: Smallest s used where a kernel's derivative is singular at 0 (L1).
_S_FLOOR = 1e-12


@dataclass(frozen=True)
class L2:
    """ρ(s) = s: plain least squares."""

    name = "l2"

    def evaluate(self, s):
        s = np.asarray(s, dtype=float)
        return s.copy(), np.ones_like(s), np.zeros_like(s)

    def rho(self, s):
        return np.asarray(s, dtype=float).copy()


@dataclass(frozen=True)
class L1:
    """ρ(s) = √s (eq. 9); ρ′ is floored near 0 where it is singular."""

    name = "l1"

    def evaluate(self, s):
        s = np.maximum(np.asarray(s, dtype=float), _S_FLOOR)
        root = np.sqrt(s)
        return root, 0.5 / root, -0.25 / (s * root)

    def rho(self, s):
        return np.sqrt(np.maximum(np.asarray(s, dtype=float), _S_FLOOR))


@dataclass(frozen=True)
class Huber:
    """ρ(s) = s for s ≤ τ², 2τ√s − τ² beyond (eq. 10 with the width made explicit so that ρ is
    C¹ for any τ; the paper's form is the case τ = 1)."""

    tau: float
    name = "huber"

    def evaluate(self, s):
        s = np.maximum(np.asarray(s, dtype=float), _S_FLOOR)
        t2 = self.tau * self.tau
        inner = s <= t2
        root = np.sqrt(s)
        rho = np.where(inner, s, 2 * self.tau * root - t2)
        d1 = np.where(inner, 1.0, self.tau / root)
        d2 = np.where(inner, 0.0, -0.5 * self.tau / (s * root))
        return rho, d1, d2

    def rho(self, s):
        s = np.maximum(np.asarray(s, dtype=float), _S_FLOOR)
        t2 = self.tau * self.tau
        return np.where(s <= t2, s, 2 * self.tau * np.sqrt(s) - t2)


@dataclass(frozen=True)
class Cauchy:
    """ρ(s) = τ² log(1 + s/τ²) (eq. 11)."""

    tau: float
    name = "cauchy"

    def evaluate(self, s):
        s = np.asarray(s, dtype=float)
        t2 = self.tau * self.tau
        q = 1.0 + s / t2
        return t2 * np.log1p(s / t2), 1.0 / q, -1.0 / (t2 * q * q)

    def rho(self, s):
        t2 = self.tau * self.tau
        return t2 * np.log1p(np.asarray(s, dtype=float) / t2)

    def derivatives(self, s):
        q = 1.0 + np.asarray(s, dtype=float) / (self.tau * self.tau)
        d1 = 1.0 / q
        return d1, (-1.0 / (self.tau * self.tau)) * (d1 * d1)


@dataclass(frozen=True)
class GemanMcClure:
    """ρ(s) = s τ² / (τ² + s): the Geman–McClure kernel. The paper's eq. 12 prints
    τ²/(τ² + s), which decreases with s; we use the standard increasing form, equal to it up to
    sign and a constant (so it has the same minimizers)."""

    tau: float
    name = "gm"

    def evaluate(self, s):
        s = np.asarray(s, dtype=float)
        t2 = self.tau * self.tau
        q = t2 + s
        return s * t2 / q, t2 * t2 / (q * q), -2.0 * t2 * t2 / (q * q * q)

    def rho(self, s):
        s = np.asarray(s, dtype=float)
        t2 = self.tau * self.tau
        return s * t2 / (t2 + s)

    def derivatives(self, s):
        t2 = self.tau * self.tau
        f = t2 / (t2 + np.asarray(s, dtype=float))
        d1 = f * f
        return d1, (-2.0 / t2) * (d1 * f)


def derivatives_of(kernel):
    """The kernel's ``derivatives`` (s ↦ (ρ′, ρ″)), or the same read off ``evaluate``."""
    return getattr(kernel, "derivatives", None) or (lambda s: kernel.evaluate(s)[1:])


#: τ / σ giving each width kernel 95 % asymptotic efficiency under Gaussian noise.
EFFICIENCY_TAU = {"cauchy": 2.3849, "huber": 1.345, "gm": 3.787}

KERNELS = {"l2": L2, "l1": L1, "huber": Huber, "cauchy": Cauchy, "gm": GemanMcClure}
#: Kernels whose width τ matters.
WIDTH_KERNELS = ("huber", "cauchy", "gm")


def make_kernel(name: str, tau: float | None = None):
    """Build a kernel by name (``l2``, ``l1``, ``huber``, ``cauchy``, ``gm``)."""
    try:
        cls = KERNELS[name]
    except KeyError:
        from ..errors import InputError

        raise InputError(f"unknown kernel {name!r}; choose one of {', '.join(KERNELS)}") from None
    if name in WIDTH_KERNELS:
        if tau is None or not np.isfinite(tau) or tau <= 0:
            raise ValueError(f"kernel {name!r} needs a positive width tau, got {tau!r}")
        return cls(float(tau))
    return cls()


def width_from_residuals(kernel: str, r_norm: np.ndarray) -> float:
    """Kernel width τ (sensor unit) for residual norms ``r_norm`` (N,): the 95 %-efficiency
    multiple of σ̂ = median / :data:`HALF_NORMAL_MEDIAN` (Cauchy's multiple for a kernel
    without a width)."""
    sigma = max(float(np.median(r_norm)) / HALF_NORMAL_MEDIAN, 1e-12)
    return EFFICIENCY_TAU.get(kernel, EFFICIENCY_TAU["cauchy"]) * sigma


def kernel_weights(kernel: str, r_norm: np.ndarray, width: float) -> np.ndarray:
    """IRLS weights ρ′(‖r‖²) (N,) of ``kernel`` at width ``width`` (ignored by L1/L2)."""
    return make_kernel(kernel, width if kernel in WIDTH_KERNELS else None).evaluate(
        np.asarray(r_norm, dtype=float) ** 2)[1]


#: Lower bound on D = 1 + 2 s ρ″/ρ′ in the Triggs correction. Where the kernel's curvature is
#: negative enough to make D ≤ 0 (Cauchy or GM beyond the width), eq. 24 has no real root;
#: clamping D keeps the corrected Gauss–Newton matrix positive semi-definite and the gradient
#: exact (it does not depend on α), at the cost of a flatter model along r for far outliers.
D_MIN = 0.25


def triggs_correction(s, d1, d2):
    """Scale factors of the Triggs correction (eq. 22–24) for residuals with s = ‖r‖².

    Returns ``(r_scale, j_alpha, sqrt_d1)`` (each (N,)) such that the corrected residual is
    ``r̃ = r_scale · r`` and the corrected Jacobian is ``J̃ = sqrt_d1 · (I − j_alpha · r rᵀ) J``,
    where ``j_alpha = α / s``. Then J̃ᵀr̃ = ρ′ Jᵀr and J̃ᵀJ̃ = Jᵀ(ρ′ + 2ρ″ r rᵀ)J (eq. 25–26).
    """
    d1 = np.maximum(d1, 1e-300)
    sqrt_d1 = np.sqrt(d1)
    D = np.maximum(1.0 + 2.0 * s * d2 / d1, D_MIN)
    alpha = 1.0 - np.sqrt(D)
    positive = s > _S_FLOOR
    j_alpha = np.where(positive, alpha / np.where(positive, s, 1.0), 0.0)
    r_scale = sqrt_d1 / (1.0 - alpha)
    return r_scale, j_alpha, sqrt_d1


def triggs_weights(s, d1, d2):
    """The Triggs correction (eq. 22–26) folded into per-sample weights, (N,) each.

    With ``r_scale, j_alpha, sqrt_d1 = triggs_correction(s, d1, d2)``, r̃ = r_scale·r and
    J̃ = sqrt_d1·(I − j_alpha·r rᵀ)J, returns ``(w, e, gw)`` such that

        J̃ᵀJ̃ = Jᵀ W J,  W = w I + e r rᵀ,      J̃ᵀr̃ = gw Jᵀr.

    Multiplied out (α = 1 − √D, D = max(1 + 2sρ″/ρ′, D_MIN)): w = gw = ρ′ and
    e = −ρ′(1 − D)/s, that is 2ρ″ where the clamp is inactive and −(1 − D_MIN)ρ′/s where it
    holds: the larger of the two. Three array operations instead of the fifteen of the factors,
    equal to them to rounding (and exact where 1 − √D cancels, at small s). At s ≤ the floor
    the factors drop r rᵀ (e = 0) and leave gw = ρ′/√D; so does this."""
    w = np.maximum(d1, 1e-300)
    e = np.maximum(2.0 * d2, (D_MIN - 1.0) * w / np.maximum(s, _S_FLOOR))
    low = s <= _S_FLOOR
    if not low.any():
        return w, e, w
    gw = w.copy()
    e[low] = 0.0
    gw[low] /= np.sqrt(np.maximum(1.0 + 2.0 * s[low] * d2[low] / w[low], D_MIN))
    return w, e, gw
