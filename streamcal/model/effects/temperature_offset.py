"""``temperature_offset`` (docs/effects.md): the offset drifts linearly with temperature,

    f_j = c (T_j − T0),      c (3,) sensor unit per °C,

``T0`` the median temperature of the data the term was built from (°C, stored with ``c``), so
the constant part stays in ``b``. Normalization divides ``c`` by ``scale``.
"""
from __future__ import annotations

import numpy as np

from ..declaration import EffectDeclaration, SimulatorTruth
from ..linear_term import LinearTerm


class TemperatureOffset(LinearTerm):
    """``f_j = c (T_j − T0)``: offset drifting linearly with temperature."""

    name = "temperature_offset"
    COLUMN, REF, PARAM = "temp", "T0", "c"


def _sim_field(u, cov, p):
    return (cov["temp"] - p["T0"])[:, None] * np.asarray(p["c"])


EFFECT = EffectDeclaration(
    name="temperature_offset", meaning="offset changes linearly with temperature", n_params="3",
    term=TemperatureOffset, needs=("temp",),
    units={"T0": "°C", "c": "{u}/°C"},
    bound=1.0,  # an added field as large as the Earth's: the compass would not point at all
    subject="temp",
    simulated=SimulatorTruth("vector", lambda v, env: {"T0": env.T0_C, "c": v.tolist()},
                             _sim_field, magnitude="|c|, µT/°C"))
