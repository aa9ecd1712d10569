"""One sensor shape, two offsets: the shared-shape refinement of the coherent-disturbance path.

A magnet riding on the board for a contiguous span of time shifts the field by a constant
vector Δ in the body frame (a pure hard-iron shift): the disturbed samples lie on
m = K x + b + Δ, the undisturbed ones on m = K x + b. When the undisturbed motion is only a cap,
K is poorly determined from it alone, while the disturbed span often covers most of the sphere;
fitting K, b and Δ jointly lets the disturbed samples pin the shape. Δ needs its own start
(:func:`shift_start`, K and b fixed): from zero the disturbed samples stay outliers of a robust
kernel and never pull Δ.

:class:`DisturbanceShift` is the internal model term ``Δ·1[j disturbed]`` for the LM
(``streamcal.fitting.lm.refine``), with the indicator passed as the covariate :data:`INDICATOR`.
All quantities are in the LM's (normalized) units.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import MAD_TO_SIGMA
from .kernels import EFFICIENCY_TAU

#: Covariate name of the disturbed-span indicator (N,) of 0/1.
INDICATOR = "_disturbed_span"
#: The shared-shape fit is kept only when the disturbed samples' median residual is within this
#: factor of the undisturbed samples' (a pure shift fits both shells to the noise).
CONSISTENCY_RATIO = 1.5
#: ... and when the support's median residual grows by at most this factor over the support-only
#: fit's (the joint fit is free to adopt the disturbed span's shape otherwise: see consistent).
SUPPORT_RATIO = 1.1
#: ... and when at least this fraction of the disturbed span fits the shifted shell.
MIN_DISTURBED_INLIERS = 0.5


class DisturbanceShift:
    """Model term f_j = Δ · s_j, s_j ∈ {0, 1} the covariate :data:`INDICATOR`; θ = Δ (3,)."""

    name = "_disturbance_shift"

    def n_params(self) -> int:
        return 3

    def initial(self) -> np.ndarray:
        return np.zeros(3)

    @staticmethod
    def _s(cov: Mapping[str, np.ndarray]) -> np.ndarray:
        return np.asarray(cov[INDICATOR], dtype=float)

    def term(self, theta, u, cov):
        """(N,3) Δ on the disturbed samples, 0 elsewhere."""
        return self._s(cov)[:, None] * np.asarray(theta)[None, :]

    def jac_theta(self, theta, u, cov):
        """(N,3,3): s_j I."""
        return self._s(cov)[:, None, None] * np.eye(3)[None, :, :]

    def jac_u(self, theta, u, cov):
        return None


def shift_start(K: np.ndarray, b: np.ndarray, m: np.ndarray, iters: int = 30) -> np.ndarray:
    """Robust offset Δ (3,) of samples m (M,3) on the shell m = K x + b + Δ with K, b fixed.

    In the frame y = K⁻¹(m − b) the shell is the unit sphere centred on c = K⁻¹Δ: an algebraic
    least-squares start (‖y‖² − 1 = 2yᵀc − ‖c‖², linear in c and ‖c‖²), then iteratively
    reweighted Gauss–Newton on the radial residuals ‖y − c‖ − 1 with Cauchy weights at the
    efficiency width of a robust (MAD) noise scale, so stray samples of the other shell count
    little."""
    y = np.linalg.solve(K, (np.asarray(m, float) - b).T).T
    A = np.column_stack([2.0 * y, -np.ones(len(y))])
    c = np.linalg.lstsq(A, np.sum(y * y, axis=1) - 1.0, rcond=None)[0][:3]
    for _ in range(iters):
        d = y - c
        rad = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        r = rad - 1.0
        sigma = max(MAD_TO_SIGMA * float(np.median(np.abs(r))), 1e-9)
        tau = EFFICIENCY_TAU["cauchy"] * sigma
        w = 1.0 / (1.0 + (r / tau) ** 2)
        J = -d / rad[:, None]                               # ∂r/∂c, (M,3)
        step = np.linalg.lstsq(J * np.sqrt(w)[:, None], -r * np.sqrt(w), rcond=None)[0]
        c = c + step
        if np.linalg.norm(step) < 1e-10:
            break
    return K @ c


def consistent(r_norm: np.ndarray, disturbed: np.ndarray, limit: float, support: np.ndarray,
               r_support_fit: np.ndarray) -> bool:
    """Whether a shared-shape fit explains both shells as well as the support fit explains its
    own samples.

    ``r_norm`` (N,): residual norms of the joint fit; ``disturbed`` (N,) bool: the span given
    the shift; ``limit``: the joint fit's inlier threshold; ``support`` (N,) bool: the samples
    the support-only fit was run on, ``r_support_fit`` (N,) its residual norms there (any value
    elsewhere). A cap plus rests hardly constrains the shape, so a disturbance that is not a
    pure shift can still be fitted by the joint model with the disturbed span's shape; the
    support's residuals then grow (SUPPORT_RATIO)."""
    r_in, r_out = r_norm[~disturbed], r_norm[disturbed]
    if len(r_in) == 0 or len(r_out) == 0 or not support.any():
        return False
    return bool(np.median(r_out) <= CONSISTENCY_RATIO * np.median(r_in)
                and np.mean(r_out <= limit) >= MIN_DISTURBED_INLIERS
                and np.median(r_norm[support]) <= SUPPORT_RATIO * np.median(r_support_fit[support]))
