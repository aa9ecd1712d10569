"""``time_drift`` (docs/effects.md): the offset changes linearly with time,

    f_j = d (t_j − t0),      d (3,) sensor unit per second,

``t0`` the median time of the data the term was built from (s, stored with ``d``).
Normalization divides ``d`` by ``scale``.
"""
from __future__ import annotations

import numpy as np

from ..declaration import EffectDeclaration, SimulatorTruth
from ..linear_term import LinearTerm


class TimeDrift(LinearTerm):
    """Offset changing linearly with time."""

    name = "time_drift"
    COLUMN, REF, PARAM = "t", "t0", "d"


def _sim_field(u, cov, p):
    return (cov["t"] - p["t0"])[:, None] * np.asarray(p["d"])


EFFECT = EffectDeclaration(
    name="time_drift", meaning="offset changes linearly with time", n_params="3", term=TimeDrift,
    units={"t0": "s", "d": "{u}/s"},
    bound=1.0,  # an added field as large as the Earth's: the compass would not point at all
    subject="time",
    simulated=SimulatorTruth("vector", lambda v, env: {"t0": env.t0_s, "d": v.tolist()},
                             _sim_field, magnitude="|d|, µT/s"))
