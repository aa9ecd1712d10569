"""The contract every non-core effect term fulfils (STYLE practice 3).

The robust LM (``streamcal.fitting.lm``) fits

    m_j = u_j + b + Σ_e f_e(θ_e, u_j, c_j) + ε_j,      u_j = K x_j,

over k (the 6 entries of K), b, every θ_e and the unit directions x_j. An effect only has to
say how its term depends on its parameters θ_e, on the undistorted reading u_j = K x_j and on the
per-sample covariates c_j (track columns aligned to the magnetometer instants: ``t``, ``temp``,
aux channels…). The LM applies the chain rule:

    ∂r/∂x = (I + Σ_e ∂f_e/∂u) K,    ∂r/∂k = (I + Σ_e ∂f_e/∂u) (xᵀ ⊗ I) Π,    ∂r/∂θ_e = ∂f_e/∂θ_e.

The LM runs on normalized data (``m_n = (m − center) / scale``, paper §II-B), so each effect
also says how its parameters convert back to physical units.

Registration effects (``mag_accel_misalignment``, ``time_lag``) change how the directions are
parameterized (tied to gravity) and are fitted by their own solver, not through this contract.
"""
from __future__ import annotations

from typing import Mapping, Protocol

import numpy as np

Covariates = Mapping[str, np.ndarray]  # column name -> (N,) values at the magnetometer instants


class Effect(Protocol):
    name: str

    def n_params(self) -> int:
        """Number of parameters P of this effect (fixed once the effect is built)."""

    def initial(self) -> np.ndarray:
        """(P,) starting parameters (normalized units); usually zeros."""

    def term(self, theta: np.ndarray, u: np.ndarray, cov: Covariates) -> np.ndarray:
        """(N,3) contribution to the measurement, given u = K x (N,3)."""

    def jac_theta(self, theta: np.ndarray, u: np.ndarray, cov: Covariates) -> np.ndarray:
        """(N,3,P) derivative of the term with respect to θ."""

    def jac_u(self, theta: np.ndarray, u: np.ndarray, cov: Covariates) -> np.ndarray | None:
        """(N,3,3) derivative of the term with respect to u, or None when the term does not
        depend on u (purely additive effects)."""

    def to_physical(self, theta: np.ndarray, scale: float) -> dict:
        """JSON-able parameters in physical units, given the normalization scale."""

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        """Inverse of :meth:`to_physical`."""
