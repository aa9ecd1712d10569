"""PX4 parameters for the first magnetometer (``CAL_MAG0_*``), as a QGroundControl ``.params``
file (tab-separated ``vehicle-id  component-id  name  value  type``).

PX4 (``sensors`` module, ``sensor_calibration`` Magnetometer) corrects a raw sensor-frame
reading ``r`` in gauss as ``f = R · S · (r + p · c − o)``:

* ``o`` = CAL_MAG0_XOFF/YOFF/ZOFF (G, *subtracted*);
* ``S`` symmetric with diagonal CAL_MAG0_XSCALE/YSCALE/ZSCALE and off-diagonal
  CAL_MAG0_XODIAG = S12, YODIAG = S13, ZODIAG = S23;
* ``R`` the board or CAL_MAG0_ROT rotation (left as it is on the vehicle);
* power compensation ``c`` = CAL_MAG0_XCOMP/YCOMP/ZCOMP, *added* to the raw reading in the
  sensor frame, before the offset, scale and rotation, times the power signal ``p`` chosen by
  CAL_MAG_COMP_TYP: 1 throttle (0..1, ``c`` in G), 2 battery current of battery_status
  instance 0 in kA (the battery's A × 0.001, ``c`` in G/kA), 3 that of instance 1 (streamcal's
  ``battery2_current_a``). PX4 sets ``p = 0`` while disarmed.

Sources checked (facts only): PX4-Autopilot ``src/lib/sensor_calibration/Magnetometer.hpp``
(the order and sign of the correction), ``src/modules/sensors/vehicle_magnetometer/
VehicleMagnetometer.cpp`` (throttle as is, current × 0.001 → kA), ``sensor_params_mag0.c`` /
``sensor_params_mag.c`` (units G and G/kA; CAL_MAG_COMP_TYP values), and the
``mag_compensation.py`` identification script (fits raw sensor_mag in the sensor frame and
writes the negated slope). The parameter text says "body frame axis", but the code adds the
term before the rotation, so it is a sensor-frame vector like streamcal's ``g``.

Streamcal's channel term ``g (a − a0)`` (µT per channel unit, sensor frame; ``g a0`` is folded
into the offset) becomes ``c = −g / 100`` for throttle (G at full throttle) and
``c = −10 g`` for current (µT/A → G/kA). 1 G = 100 µT. One channel only, as in ArduPilot.
"""
from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ..inputs.autopilot_cal import PX4_KA_PER_A as KA_PER_A, UT_PER_GAUSS, px4_matrix, px4_offsets
from .common import (ascii_text, correction, fmt, hold_others, joint_fit_note, motor_channel,
                     mounting, orientation_words)

FLOAT_TYPE = 9  # MAV_PARAM_TYPE_REAL32
INT_TYPE = 6  # MAV_PARAM_TYPE_INT32
#: CAL_MAG_COMP_TYP of each motor-compensation channel kind (export.common.motor_channel).
COMP_TYP = {"throttle": 1, "current": 2, "current2": 3}


def apply_px4(params: dict, r_gauss: np.ndarray, power=None) -> np.ndarray:
    """PX4's documented correction (without the rotation) of readings (N,3) G: (N,3) G.

    ``power`` (N,) is PX4's power signal for CAL_MAG_COMP_TYP: throttle 0..1 (type 1) or the
    battery current in kA (type 2/3); ignored when absent or the type is 0.
    """
    S, off = px4_matrix(params), px4_offsets(params)
    r = np.asarray(r_gauss, dtype=float)
    if power is not None and params.get("CAL_MAG_COMP_TYP", 0):
        comp = np.array([params[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])
        r = r + np.asarray(power, dtype=float)[:, None] * comp
    return (r - off) @ S.T


def _compensation(corr, notes: list) -> tuple[int, str | None, np.ndarray | None]:
    """(CAL_MAG_COMP_TYP, chosen channel, CAL_MAG0_*COMP (3,)) from the aux channels."""
    chosen, kind, others = motor_channel(corr.channels, second_battery=True)
    hold_others(corr, chosen)
    notes.extend(f"aux_interference on {name!r}: PX4 compensates one channel, throttle "
                 "(0..1) or the current of battery 1 or 2 (A, as kA); held at its level a0"
                 for name in others)
    notes.extend(joint_fit_note(chosen, others))
    if chosen is None:
        return 0, None, None
    comp_type = COMP_TYP[kind]
    g = np.asarray(corr.channels[chosen], dtype=float)
    # r + p c must cancel g a: p c = −g a / 100 (G), p = a (throttle) or a·0.001 (kA)
    comp = -g / UT_PER_GAUSS / (KA_PER_A if kind != "throttle" else 1.0)
    return comp_type, chosen, comp


def export(cal: Calibration) -> tuple[str, list[str]]:
    """(file text, notes on what PX4 cannot express)."""
    corr = correction(cal)
    S, notes = corr.S, list(corr.not_expressed)
    comp_type, chosen, comp = _compensation(corr, notes)
    rot, orient, more = mounting(cal, "px4")   # PX4 rotates after offsets and scale
    notes += more
    params = {}
    for k, a in enumerate("XYZ"):
        params[f"CAL_MAG0_{a}OFF"] = corr.offset[k] / UT_PER_GAUSS
    for k, a in enumerate("XYZ"):
        params[f"CAL_MAG0_{a}SCALE"] = S[k, k]
    params["CAL_MAG0_XODIAG"], params["CAL_MAG0_YODIAG"], params["CAL_MAG0_ZODIAG"] = \
        S[0, 1], S[0, 2], S[1, 2]
    in_readings = (cal.extra or {}).get("motor_field_in_readings") if chosen is None else None
    if chosen is not None or in_readings:
        for k, a in enumerate("XYZ"):
            params[f"CAL_MAG0_{a}COMP"] = comp[k] if chosen is not None else 0.0
    lines = [f"# streamcal calibration for PX4 (CAL_MAG0), {cal.created}",
             "# PX4 corrects f = R S (r + p CAL_MAG0_COMP - CAL_MAG0_OFF), offsets in gauss; "
             "CAL_MAG0_ID (and _ROT unless a mounting rotation was found) are left as they "
             "are on the vehicle",
             f"# S is the symmetric (polar) form of |B| K^-1, |B| = {corr.field_uT:.6g} uT"
             + ("" if corr.field_known else " (K's mean radius: field strength unknown)"),
             "# the rotation between streamcal's and this frame is unobservable from the "
             "magnetometer alone and is not exported"]
    if chosen is not None:
        lines.append(f"# CAL_MAG0_*COMP from aux_interference on {chosen!r} (CAL_MAG_COMP_TYP "
                     f"{comp_type}: "
                     + (f"battery_status instance {comp_type - 2} current in kA, G/kA"
                        if comp_type >= 2 else "throttle 0..1, G at full throttle")
                     + "; PX4 applies it only while armed)")
    if in_readings:
        lines.append("# CAL_MAG0_*COMP set to 0: this calibration has no motor term, and was "
                     f"fitted on readings that carry the motor field ({in_readings} of the log "
                     "not in them), so its offsets hold the field's mean; the old compensation "
                     "would remove it a second time. For a motor term refit with --cal "
                     "autopilot --add aux_interference=CHANNEL")
    index = int((cal.extra or {}).get("compass_params_index", 0))
    if index:   # the compass the calibration was fitted for keeps it in CAL_MAG<index>_*
        params = {k.replace("CAL_MAG0_", f"CAL_MAG{index}_"): v for k, v in params.items()}
        lines = [line.replace("CAL_MAG0", f"CAL_MAG{index}") for line in lines]
    lines.append("# Vehicle-Id\tComponent-Id\tName\tValue\tType")
    lines += [f"# NOT EXPRESSED: {note}" for note in notes]
    lines += [f"1\t1\t{name}\t{fmt(value)}\t{FLOAT_TYPE}" for name, value in params.items()]
    if chosen is not None:
        lines.append(f"1\t1\tCAL_MAG_COMP_TYP\t{comp_type}\t{INT_TYPE}")
    if orient is not None:
        lines.insert(2, f"# CAL_MAG{index}_ROT {orient}: the compass is mounted rotated "
                        f"({orientation_words(cal)}); PX4 applies it after the "
                        "offsets and scale")
        lines.append(f"1\t1\tCAL_MAG{index}_ROT\t{orient}\t{INT_TYPE}")
    return ascii_text("\n".join(lines) + "\n"), notes
