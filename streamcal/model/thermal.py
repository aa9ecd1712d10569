"""Temperature effects (docs/effects.md ``temperature_offset``, ``temperature_scale``).

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

from .linear_term import LinearTerm

_EYE = np.eye(3)


class TemperatureOffset(LinearTerm):
    """``f_j = c (T_j − T0)``: offset drifting linearly with temperature."""

    name = "temperature_offset"
    COLUMN, REF, PARAM = "temp", "T0", "c"


class TemperatureScale(LinearTerm):
    """``f_j = diag(s) (T_j − T0) u_j``: per-axis gain changing linearly with temperature."""

    name = "temperature_scale"
    COLUMN, REF, PARAM = "temp", "T0", "s"

    def term(self, theta, u, cov):
        return self.delta(cov)[:, None] * np.asarray(theta)[None, :] * u

    def jac_theta(self, theta, u, cov):
        return (self.delta(cov)[:, None] * u)[:, :, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return (self.delta(cov)[:, None] * np.asarray(theta)[None, :])[:, :, None] * _EYE[None]

    def to_physical(self, theta, scale: float) -> dict:
        return {self.REF: self.ref, self.PARAM: [float(v) for v in np.asarray(theta)]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        return self._physical_vector(params)
