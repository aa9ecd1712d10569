"""How quantities are written for a human reader: one spelling per unit, sensible digits.

Every text a person reads (command output, ``print(cal)``, the report) formats numbers through
this module, so ``time_lag`` prints as ``tau 10.9 ms`` and not ``tau=0.010945823840833167``, and
the microtesla is always written ``µT``. Machine output (JSON keys and values, CSV headers) keeps
its own spelling (``uT``, ``field_uT``); nothing here is used for it.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

#: The unit of a track or calibration that does not say it in words streamcal knows
#: (``# mag_unit: probably uT``): written nowhere after a number; where the source is named,
#: "unit unknown" is said once instead.
UNKNOWN = "unknown"

#: Display form of a unit name as it appears in tracks and calibration files.
_DISPLAY = {"uT": "µT", "μT": "µT", "ut": "µT", "m/s2": "m/s²", "m/s^2": "m/s²", "degC": "°C"}

#: Significant digits of a number written for a reader.
DIGITS = 3

def display_unit(unit: str | None) -> str:
    """The unit as a reader writes it: ``uT`` → ``µT``, ``m/s^2`` → ``m/s²``; others unchanged;
    "" for None and :data:`UNKNOWN`."""
    if unit is None or unit == UNKNOWN:
        return ""
    return _DISPLAY.get(unit, unit)


def with_unit(text: str, unit: str | None) -> str:
    """``text`` followed by the display form of ``unit`` (``"0.37 µT"``); ``text`` alone when the
    unit is unknown or none."""
    shown = display_unit(unit)
    return f"{text} {shown}" if shown else text


def param_unit(effect: str, param: str, sensor_unit: str = "uT") -> str:
    """Display unit of parameter ``param`` of ``effect`` ("" when dimensionless or unknown): the
    effect's declared ``units`` (:mod:`streamcal.model.effects`; ``{u}`` stands for the sensor
    unit). Angles are stored in radians and shown in degrees; seconds are shown with an SI
    prefix (``ms``, ``µs``)."""
    # Imported here: the catalog loads every effect's term, which plain formatting never needs.
    from .model.catalog import BY_NAME

    info = BY_NAME.get(effect)
    unit = info.units.get(param, "") if info is not None else ""
    return unit.replace("{u}", display_unit(sensor_unit))


def number(value: float, digits: int = DIGITS) -> str:
    """``value`` to ``digits`` significant digits (``–`` when not finite)."""
    v = float(value)
    if not math.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


def scaled(values, unit: str | None) -> tuple[np.ndarray, str]:
    """``(values, unit)`` converted to the form a reader expects: rad → °, s → ms or µs when
    every value is that small, the unit in its display spelling (``uT`` → ``µT``)."""
    return _scaled(np.asarray(values, dtype=float), display_unit(unit))


def _scaled(values: np.ndarray, unit: str) -> tuple[np.ndarray, str]:
    if unit == "rad":
        return np.degrees(values), "°"
    if unit == "s":
        finite = np.abs(values[np.isfinite(values)])
        big = float(finite.max()) if finite.size else 0.0
        if 0 < big < 1e-3:
            return values * 1e6, "µs"
        if 0 < big < 1.0:
            return values * 1e3, "ms"
    return values, unit


def quantity(value, unit: str | None = "", digits: int = DIGITS) -> str:
    """A number or vector with its unit: ``quantity(0.0109458, "s")`` → ``"10.9 ms"``,
    ``quantity([1, 2, 3], "uT")`` → ``"[1, 2, 3] µT"``. Angles in ``rad`` are shown in degrees."""
    arr = np.asarray(value, dtype=float)
    arr, shown = _scaled(arr, display_unit(unit))
    if arr.ndim == 0:
        text = number(arr, digits)
    else:
        text = "[" + ", ".join(number(v, digits) for v in arr.ravel()) + "]"
    if not shown:
        return text
    return text + ("" if shown == "°" else " ") + shown


def effect_params(effect: str, params: Mapping[str, Any], sensor_unit: str = "uT",
                  digits: int = DIGITS) -> str:
    """One line of an effect's parameters with units: ``tau 10.9 ms`` or
    ``T0 24.1 °C, c [0.12, -0.0341, 0.05] µT/°C``. ``aux_interference`` lists its channels."""
    parts = []
    for key, value in params.items():
        if key == "channels" and isinstance(value, Mapping):
            for channel, sub in value.items():
                inner = ", ".join(f"{k} {quantity(v, param_unit(effect, k, sensor_unit), digits)}"
                                  for k, v in sub.items())
                parts.append(f"{channel}: {inner}")
            continue
        try:
            text = quantity(value, param_unit(effect, key, sensor_unit), digits)
        except (TypeError, ValueError):
            text = str(value)
        parts.append(f"{key} {text}")
    return ", ".join(parts)
