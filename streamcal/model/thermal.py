"""Temperature effects (SPEC §3 ``temperature_offset``, ``temperature_scale``).

Both are linear in ``ΔT = T − T0`` with ``T0`` the median temperature of the data they were
built from (°C, stored with the parameters), so the constant part stays in ``b`` / ``K``:

    temperature_offset:  f = c ΔT                  c (3,) sensor unit per °C
    temperature_scale:   f = diag(s) ΔT u          s (3,) per °C (relative gain change)

Normalization (``m_n = (m − center)/scale``) divides ``c`` by ``scale`` and leaves ``s``
unchanged (``u`` scales like ``m``).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ._common import column, number, only_keys, same_constant, vector3

_EYE = np.eye(3)


class _TemperatureTerm:
    """What both temperature terms share: ``T0``, ``ΔT`` and one 3-vector parameter ``PARAM``."""

    name = ""
    PARAM = ""

    def __init__(self, T0: float):
        self.T0 = float(T0)

    @classmethod
    def build(cls, cov: Mapping[str, np.ndarray]):
        return cls(float(np.nanmedian(column(cov, "temp", cls.name))))

    @classmethod
    def from_params(cls, params: Mapping):
        only_keys(params, ("T0", cls.PARAM), cls.name)
        vector3(params, cls.PARAM, cls.name)
        return cls(number(params, "T0", cls.name))

    def n_params(self) -> int:
        return 3

    def initial(self) -> np.ndarray:
        return np.zeros(3)

    def _dT(self, cov):
        return column(cov, "temp", self.name) - self.T0

    def _physical_vector(self, params: Mapping) -> np.ndarray:
        same_constant(self.T0, number(params, "T0", self.name), "T0", self.name)
        return vector3(params, self.PARAM, self.name)


class TemperatureOffset(_TemperatureTerm):
    """``f_j = c (T_j − T0)``: offset drifting linearly with temperature."""

    name = "temperature_offset"
    PARAM = "c"

    def term(self, theta, u, cov):
        return self._dT(cov)[:, None] * np.asarray(theta)[None, :]

    def jac_theta(self, theta, u, cov):
        return self._dT(cov)[:, None, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return None

    def to_physical(self, theta, scale: float) -> dict:
        return {"T0": self.T0, "c": [float(v) for v in np.asarray(theta) * scale]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        return self._physical_vector(params) / scale


class TemperatureScale(_TemperatureTerm):
    """``f_j = diag(s) (T_j − T0) u_j``: per-axis gain changing linearly with temperature."""

    name = "temperature_scale"
    PARAM = "s"

    def term(self, theta, u, cov):
        return self._dT(cov)[:, None] * np.asarray(theta)[None, :] * u

    def jac_theta(self, theta, u, cov):
        return (self._dT(cov)[:, None] * u)[:, :, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return (self._dT(cov)[:, None] * np.asarray(theta)[None, :])[:, :, None] * _EYE[None]

    def to_physical(self, theta, scale: float) -> dict:
        return {"T0": self.T0, "s": [float(v) for v in np.asarray(theta)]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        return self._physical_vector(params)
