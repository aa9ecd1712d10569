"""Time drift (docs/effects.md ``time_drift``): ``f_j = d (t_j − t0)``.

``t0`` is the median time of the data the term was built from (s, stored), ``d`` (3,) is in the
sensor unit per second; normalization divides ``d`` by ``scale``.
"""
from __future__ import annotations

from .linear_term import LinearTerm


class TimeDrift(LinearTerm):
    """Offset changing linearly with time."""

    name = "time_drift"
    COLUMN, REF, PARAM = "t", "t0", "d"
