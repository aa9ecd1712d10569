"""``axis_nonlinearity`` (docs/effects.md): a cubic gain error per axis.

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

from .._common import number, only_keys, vector3
from ..declaration import EffectDeclaration, SimulatorTruth

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


def _sim_field(u, cov, p):
    return np.asarray(p["a"]) * u ** 3 / p["R"] ** 2


EFFECT = EffectDeclaration(
    name="axis_nonlinearity", meaning="cubic term per axis", n_params="3", term=AxisNonlinearity,
    units={"R": "{u}", "a": ""}, notes={"a": "dimensionless (of (m/R)³)"},
    # A cubic bend of 5 % of the field at field-level readings: magnetometer linearity is
    # specified as a fraction of full scale (order 0.1–1 % FS), a cubic error shrinks as
    # (|u|/FS)² below it, and the Earth's field is ~1 % of an AK8963's 4912 µT full scale.
    bound=0.05,
    subject="the cube of each axis reading",
    simulated=SimulatorTruth("vector", lambda v, env: {"R": float(env.field_uT), "a": v.tolist()},
                             _sim_field, magnitude="|a|, dimensionless (R = the field radius)"))
