"""The effect catalog of docs/effects.md: names (part of the interface), parameter counts and needs.

``needs`` lists track columns; ``"aux"`` means at least one auxiliary channel, and
``("gyro", "accel")`` in ``needs_any`` means either group of columns will do.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EffectInfo:
    name: str
    meaning: str
    n_params: str
    needs: tuple[str, ...] = ()
    needs_any: tuple[str, ...] = ()


CATALOG: tuple[EffectInfo, ...] = (
    EffectInfo("hard_iron", "constant offset b", "3"),
    EffectInfo("scale", "per-axis gain only (diagonal K)", "3"),
    EffectInfo("soft_iron", "full upper-triangular K: gains, soft iron, non-orthogonality", "6"),
    EffectInfo("temperature_offset", "offset changes linearly with temperature", "3", ("temp",)),
    EffectInfo("temperature_scale", "per-axis gain changes linearly with temperature", "3", ("temp",)),
    EffectInfo("time_drift", "offset changes linearly with time", "3"),
    EffectInfo("aux_interference", "field proportional to an auxiliary channel", "3 per channel", ("aux",)),
    EffectInfo("axis_nonlinearity", "cubic term per axis", "3"),
    EffectInfo("mag_accel_misalignment", "rotation between magnetometer and accelerometer frames",
               "3 (+ dip)", ("accel",)),
    EffectInfo("time_lag", "magnetometer samples lag the IMU clock", "1", (), ("gyro", "accel")),
)

EFFECT_NAMES: tuple[str, ...] = tuple(e.name for e in CATALOG)
#: Effects carried by K and b themselves.
CORE_EFFECTS = ("hard_iron", "scale", "soft_iron")
BY_NAME = {e.name: e for e in CATALOG}
