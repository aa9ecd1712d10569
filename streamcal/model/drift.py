"""Time drift (SPEC §3 ``time_drift``): ``f_j = d (t_j − t0)``.

``t0`` is the median time of the data the term was built from (s, stored), ``d`` (3,) is in the
sensor unit per second; normalization divides ``d`` by ``scale``.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ._common import column, number, only_keys, same_constant, vector3

_EYE = np.eye(3)


class TimeDrift:
    """Offset changing linearly with time."""

    name = "time_drift"

    def __init__(self, t0: float):
        self.t0 = float(t0)

    @classmethod
    def build(cls, cov: Mapping[str, np.ndarray]) -> "TimeDrift":
        return cls(float(np.nanmedian(column(cov, "t", cls.name))))

    @classmethod
    def from_params(cls, params: Mapping) -> "TimeDrift":
        only_keys(params, ("t0", "d"), cls.name)
        vector3(params, "d", cls.name)
        return cls(number(params, "t0", cls.name))

    def n_params(self) -> int:
        return 3

    def initial(self) -> np.ndarray:
        return np.zeros(3)

    def _dt(self, cov):
        return column(cov, "t", self.name) - self.t0

    def term(self, theta, u, cov):
        return self._dt(cov)[:, None] * np.asarray(theta)[None, :]

    def jac_theta(self, theta, u, cov):
        return self._dt(cov)[:, None, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return None

    def to_physical(self, theta, scale: float) -> dict:
        return {"t0": self.t0, "d": [float(v) for v in np.asarray(theta) * scale]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        same_constant(self.t0, number(params, "t0", self.name), "t0", self.name)
        return vector3(params, "d", self.name) / scale
