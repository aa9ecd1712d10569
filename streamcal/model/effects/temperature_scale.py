"""``temperature_scale`` (docs/effects.md): the per-axis gain changes linearly with temperature,

    f_j = diag(s) (T_j − T0) u_j,      s (3,) per °C (relative gain change),

``T0`` the median temperature of the data the term was built from (°C, stored with ``s``).
Normalization leaves ``s`` unchanged (``u`` scales like ``m``).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..declaration import EffectDeclaration, SimulatorTruth
from ..linear_term import LinearTerm

_EYE = np.eye(3)


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


def _sim_field(u, cov, p):
    return (cov["temp"] - p["T0"])[:, None] * np.asarray(p["s"]) * u


EFFECT = EffectDeclaration(
    name="temperature_scale", meaning="per-axis gain changes linearly with temperature",
    n_params="3", term=TemperatureScale, needs=("temp",),
    units={"T0": "°C", "s": "1/°C"},
    # A gain change of a quarter of the field within one recording's temperatures: a sensor
    # drifting that much would need a calibration per temperature; the term is taking up
    # something else.
    bound=0.25,
    subject="temp × reading",
    simulated=SimulatorTruth("vector", lambda v, env: {"T0": env.T0_C, "s": v.tolist()},
                             _sim_field, magnitude="|s|, 1/°C"))
