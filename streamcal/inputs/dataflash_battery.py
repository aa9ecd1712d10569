"""The batteries of an ArduPilot DataFlash log (see :mod:`.dataflash`), and the rows of one
instance of a message type.

Battery 0 is ``CURR`` (older layouts; centivolts and centiamps when its fields are integers, and
its ``Throttle``/``ThrOut``: 0..1000, a plane's pilot input in percent,
:func:`~.dataflash_throttle.curr_throttle`) or the rows of ``BAT`` whose instance field is 0;
battery ``k`` ≥ 1 is the rows of ``BAT`` with instance ``k`` (4.0 on), ``BAT2`` (3.6) or ``CUR2``
(Copter 3.4–3.5). Each becomes ``battery_…`` / ``battery{k+1}_…`` ``voltage_v`` and
``current_a`` columns: a current per battery, since each can feed motors near a different
compass. A column constant over the log (no sensor fitted) or NaN throughout (ArduPilot's BAT of
a monitor that measures no current) is left out and said.

The functions take the reader's parsed messages (``has``, ``count``, ``array``, ``types``,
``cols``; a dataclass) and ``time_of(msgs, name)`` → the times (s) of ``name``'s rows in
``msgs``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .dataflash_throttle import curr_throttle
from .streams import Stream

#: Names of the instance field of a message type that has one: ``I`` (MAG, IMU, BARO, GPS),
#: ``Instance`` (BAT in ArduPilot 4.0), ``Inst`` (BAT from 4.1).
INSTANCE_FIELDS = ("I", "Inst", "Instance")
#: Integer-typed CURR Volt/Curr fields are centivolts / centiamps (older layouts).
CENTI = 0.01
_INT_TYPES = set("bBhHiIqQ")


def instance_field(msgs, name: str) -> str | None:
    """The instance field of message type ``name`` (:data:`INSTANCE_FIELDS`), None without."""
    return next((f for f in INSTANCE_FIELDS if msgs.has(name, f)), None)


def rows_of(msgs, name: str, instance: int = 0):
    """``msgs`` with only the rows of ``instance`` of ``name`` when its layout has an instance
    field (:func:`instance_field`; the other message types shared, not copied)."""
    column = instance_field(msgs, name)
    if column is None:
        return msgs
    keep = msgs.array(name, column) == instance
    cols = dict(msgs.cols)
    cols[name] = {k: v[keep] for k, v in msgs.cols[name].items()}
    return dataclasses.replace(msgs, cols=cols)


def battery_streams(msgs, time_of, meta: dict) -> list[Stream]:
    """Every battery's stream (see the module docstring), battery 0 first."""
    out = []
    for name in ("CURR", "BAT"):
        if msgs.count(name):
            out.append(_battery_stream(rows_of(msgs, name), name, "battery", time_of, meta))
    column = instance_field(msgs, "BAT")
    if msgs.count("BAT") and column is not None:
        for k in sorted(int(i) for i in np.unique(msgs.array("BAT", column)) if i >= 1):
            out.append(_battery_stream(rows_of(msgs, "BAT", k), "BAT", f"battery{k + 1}",
                                       time_of, meta))
    for name in ("CUR2", "BAT2"):
        if msgs.count(name):
            out.append(_battery_stream(msgs, name, "battery2", time_of, meta))
    return [s for s in out if s is not None]


def _battery_stream(msgs, name: str, prefix: str, time_of, meta: dict) -> Stream | None:
    types = msgs.types.get(name, {})
    cols = {}
    for field_name, quantity in (("Volt", "voltage_v"), ("Curr", "current_a")):
        if msgs.has(name, field_name):
            scale = CENTI if types.get(field_name) in _INT_TYPES else 1.0
            cols[f"{prefix}_{quantity}"] = msgs.array(name, field_name) * scale
    if prefix == "battery":
        for field_name in ("Throttle", "ThrOut"):
            if msgs.has(name, field_name):
                throttle = curr_throttle(msgs, name, field_name, meta)
                if throttle is not None:
                    cols["throttle"] = throttle
                break
    if not cols or not len(next(iter(cols.values()))):
        return None
    unmeasured = [k for k, v in cols.items() if not np.any(np.isfinite(v))]
    for k in unmeasured:
        del cols[k]
    if unmeasured:
        meta[f"{prefix}_not_measured"] = ",".join(unmeasured) + " (NaN over the whole log)"
    constant = [k for k, v in cols.items() if np.all(v == v[0])]
    for k in constant:
        del cols[k]
    if constant:
        key = f"{name.lower()}_constant_dropped" if prefix == "battery" else \
            f"{prefix}_constant_dropped"
        meta[key] = ",".join(constant) + " (constant over the log: no sensor fitted or not logged)"
    if "throttle" in constant:     # a constant throttle is no signal: let CTUN/RCOU try
        meta.pop("throttle_source", None)
    return Stream(name if prefix == "battery" else f"{name} {prefix}", time_of(msgs, name),
                  cols) if cols else None
