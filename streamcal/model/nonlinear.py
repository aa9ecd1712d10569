"""Cubic axis nonlinearity (docs/effects.md ``axis_nonlinearity``).

Each axis reading bends with the cube of its own undistorted value:

    f_ji = a_i u_ji³ / R²,      i = x, y, z

``a`` (3,) is dimensionless (the relative error at ``|u_i| = R``) and ``R`` a fixed normalization
radius stored with it, in the sensor unit. A term built for the LM uses ``R = 1`` in normalized
units, i.e. ``R`` ≈ the field radius in physical units (``R_phys = scale``). On the sphere the cube
has a part along ``x_i`` (``x_i³`` projects 3/5 onto ``x_i``) that ``K`` also explains; the fit
shares it, the harmonic rest is what makes ``a`` identifiable.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ._common import number, only_keys, vector3

_EYE = np.eye(3)


class AxisNonlinearity:
    """Per-axis cubic gain error."""

    name = "axis_nonlinearity"

    def __init__(self, R: float = 1.0):
        if not R > 0:
            raise ValueError(f"{self.name}: parameter 'R' must be positive, found {R}")
        self.R = float(R)

    @classmethod
    def build(cls, cov: Mapping[str, np.ndarray]) -> "AxisNonlinearity":
        return cls(1.0)

    @classmethod
    def from_params(cls, params: Mapping) -> "AxisNonlinearity":
        only_keys(params, ("R", "a"), cls.name)
        vector3(params, "a", cls.name)
        return cls(number(params, "R", cls.name))

    def n_params(self) -> int:
        return 3

    def initial(self) -> np.ndarray:
        return np.zeros(3)

    def term(self, theta, u, cov):
        return np.asarray(theta)[None, :] * u ** 3 / self.R ** 2

    def jac_theta(self, theta, u, cov):
        return (u ** 3 / self.R ** 2)[:, :, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return (3.0 * np.asarray(theta)[None, :] * u ** 2 / self.R ** 2)[:, :, None] * _EYE[None]

    def to_physical(self, theta, scale: float) -> dict:
        return {"R": self.R * scale, "a": [float(v) for v in np.asarray(theta)]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        # a_phys u_p³/R_p² in normalized units is a_phys u_n³ / (R_p/scale)².
        R_p = number(params, "R", self.name)
        return vector3(params, "a", self.name) * (self.R * scale / R_p) ** 2
