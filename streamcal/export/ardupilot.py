"""ArduPilot parameter file (``NAME,VALUE`` lines, as Mission Planner / MAVProxy load them).

ArduPilot (``AP_Compass_Backend::correct_field``) corrects a body-frame reading ``r`` in
milligauss as offsets → soft-iron matrix → motor compensation (Copter 3.6, Plane 3.9, Rover 3.3
and later; :data:`~streamcal.inputs.autopilot_cal.MOTOR_AFTER_MATRIX`)::

    f = S (r + COMPASS_OFS) + COMPASS_MOT · c

and, in older firmware (:data:`~streamcal.inputs.autopilot_cal.MOTOR_BEFORE_MATRIX`), as
``f = S (r + COMPASS_OFS + COMPASS_MOT · c)``. ``S`` symmetric: diagonal COMPASS_DIA_X/Y/Z,
off-diagonal COMPASS_ODI_X = S12, _Y = S13, _Z = S23. Offsets are *added* and in mG
(1 µT = 10 mG), so ``COMPASS_OFS = −10·o``. COMPASS_MOTCT selects ``c``: 1 throttle (0..1), 2
battery current (A). Streamcal's channel term ``g·a`` in the sensor frame becomes
``COMPASS_MOT = −10 · S g`` after the matrix, ``−10 · g`` before it (mG per A, or mG at full
throttle). The newest order is written unless a firmware version says otherwise. One channel
only; an aux channel named ``throttle`` (0..1) maps to MOTCT 1, ``battery_current_a`` /
``motor_current`` / ``current`` (A) to MOTCT 2.

COMPASS_MOTCT 1 needs the vehicle to pass its throttle to the compass library
(``Compass::set_throttle``), which ArduCopter does and ArduPlane and Rover do not (ArduPilot PR
19414, open since December 2021, would take it from the motors for Rover and QuadPlane VTOL
motors): for a Plane or Rover firmware (``--firmware-version``, else the log's version the
calibration carries in ``extra["firmware"]``) the file and the notes say the term is ignored.
"""
from __future__ import annotations

import re

import numpy as np

from ..calibration import Calibration
from ..errors import InputError
from ..inputs.autopilot_cal import (FIRMWARE_VERSION, MOTOR_AFTER_MATRIX, MOTOR_BEFORE_MATRIX,
                                    ardupilot_correction_order)
from .common import (ascii_text, correction, fmt, hold_others, joint_fit_note, motor_channel,
                     mounting, orientation_words)

MG_PER_UT = 10.0
#: COMPASS_MOTCT of each motor-compensation channel kind.
MOTCT = {"throttle": 1, "current": 2}


def apply_ardupilot(params: dict, r_mG: np.ndarray, c=None,
                    order: str = MOTOR_AFTER_MATRIX) -> np.ndarray:
    """ArduPilot's correction of readings ``r_mG`` (N,3) with ``params`` and the motor channel's
    values ``c`` (N,), the motor term added in ``order``: (N,3) mG."""
    S = np.diag([params[f"COMPASS_DIA_{a}"] for a in "XYZ"])
    S[0, 1] = S[1, 0] = params["COMPASS_ODI_X"]
    S[0, 2] = S[2, 0] = params["COMPASS_ODI_Y"]
    S[1, 2] = S[2, 1] = params["COMPASS_ODI_Z"]
    ofs = np.array([params[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    motor = 0.0
    if c is not None and params.get("COMPASS_MOTCT", 0):
        mot = np.array([params[f"COMPASS_MOT_{a}"] for a in "XYZ"])
        motor = np.asarray(c, dtype=float)[:, None] * mot
    if order == MOTOR_BEFORE_MATRIX:
        return (np.asarray(r_mG) + ofs + motor) @ S.T
    return (np.asarray(r_mG) + ofs) @ S.T + motor


def target_order(firmware_version: str | None) -> str:
    """The correction order of the firmware ``firmware_version`` names ("Copter 3.5",
    "ArduPlane V3.8.2"); the newest when None. InputError when it names no vehicle and
    version."""
    if firmware_version is None:
        return MOTOR_AFTER_MATRIX
    if not FIRMWARE_VERSION.search(firmware_version):
        raise InputError(f"--firmware-version {firmware_version!r}: expected an ArduPilot "
                         "vehicle and version, e.g. 'Copter 3.5' or 'ArduPlane V3.8.2'")
    return ardupilot_correction_order(firmware_version)[0]


#: Vehicles whose firmware never passes its throttle to the compass library: COMPASS_MOTCT 1
#: leaves the motor offset at 0 there (AP_Compass_Backend::correct_field scales COMPASS_MOT by
#: the throttle ``Compass::set_throttle`` set, which only ArduCopter calls).
NO_THROTTLE_FEED = ("plane", "rover")


def throttle_ignored(firmware: str | None) -> str | None:
    """"Plane 3.9" when the firmware ``firmware`` names is one that ignores COMPASS_MOTCT 1
    (:data:`NO_THROTTLE_FEED`), else None."""
    match = FIRMWARE_VERSION.search(firmware or "")
    if not match or match.group(1).lower() not in NO_THROTTLE_FEED:
        return None
    return f"{match.group(1).capitalize()} {match.group(2)}.{match.group(3)}"


def slot_suffix(cal: Calibration) -> str:
    """The parameter-set suffix of the compass ``cal`` was fitted for (``extra
    ["compass_params_index"]``): "" for the first (``COMPASS_OFS_X``), "2", "3"."""
    index = int((cal.extra or {}).get("compass_params_index", 0))
    return "" if index == 0 else str(index + 1)


def _named(params: dict, suffix: str) -> dict:
    """The first compass's parameter names turned into those of parameter set ``suffix``
    (``COMPASS_OFS2_X``, ``COMPASS_ORIENT2``; COMPASS_MOTCT is shared by all compasses)."""
    if not suffix:
        return params
    return {re.sub(r"^COMPASS_(OFS|DIA|ODI|MOT)_", rf"COMPASS_\g<1>{suffix}_", name)
            .replace("COMPASS_ORIENT", f"COMPASS_ORIENT{suffix}")
            .replace("COMPASS_SCALE", f"COMPASS_SCALE{suffix}"): value
            for name, value in params.items()}


def export(cal: Calibration, firmware_version: str | None = None, *,
           order: str | None = None) -> tuple[str, list[str]]:
    """(file text, notes on what ArduPilot cannot express), in the parameter names of the
    compass the calibration was fitted for, COMPASS_MOT in the correction order of
    ``firmware_version`` (:func:`target_order`; the newest when None) or ``order``."""
    order = order or target_order(firmware_version)
    corr = correction(cal)
    S, notes = corr.S, list(corr.not_expressed)
    rot, orient, more = mounting(cal, "ardupilot")
    notes += more
    if rot is not None:
        # ArduPilot turns the reading by COMPASS_ORIENT before the offsets and the matrix
        # (AP_Compass_Backend: rotate_field, then correct_field): express them after it
        S = rot @ S @ rot.T
        corr.offset = rot @ corr.offset
        corr.channels = {k: rot @ g for k, g in corr.channels.items()}
    chosen, kind, others = motor_channel(corr.channels)
    hold_others(corr, chosen)
    params = {}
    for k, a in enumerate("XYZ"):
        params[f"COMPASS_OFS_{a}"] = -MG_PER_UT * corr.offset[k]
    for k, a in enumerate("XYZ"):
        params[f"COMPASS_DIA_{a}"] = S[k, k]
    params["COMPASS_ODI_X"], params["COMPASS_ODI_Y"], params["COMPASS_ODI_Z"] = \
        S[0, 1], S[0, 2], S[1, 2]
    motct = MOTCT.get(kind, 0)
    notes += [f"aux_interference on {name!r}: ArduPilot compensates one channel, the first "
              "battery's current (A) or throttle (0..1); held at its level a0" for name in others]
    notes += joint_fit_note(chosen, others)
    if chosen is not None:
        g = corr.channels[chosen]
        mot = -MG_PER_UT * (S @ g if order == MOTOR_AFTER_MATRIX else g)
        for k, a in enumerate("XYZ"):
            params[f"COMPASS_MOT_{a}"] = mot[k]
        params["COMPASS_MOTCT"] = motct
        target, whose = ((firmware_version, "--firmware-version") if firmware_version else
                         ((cal.extra or {}).get("firmware"), "the log's firmware"))
        ignored = throttle_ignored(target) if motct == 1 else None
        if ignored:
            notes.append(f"COMPASS_MOTCT 1 (throttle): {ignored} ({whose}) ignores it, only "
                         "ArduCopter passes its throttle to the compass library "
                         "(Compass::set_throttle; ArduPilot PR 19414 would add Rover and "
                         "QuadPlane VTOL motors), so COMPASS_MOT stays unapplied there; fit "
                         "--add aux_interference=battery_current_a for COMPASS_MOTCT 2")
    scale = (cal.extra or {}).get("scale_in_force")
    if scale:   # ArduPilot multiplies by COMPASS_SCALEn after the offsets: S is the whole scale
        params["COMPASS_SCALE"] = 1.0
    in_readings = (cal.extra or {}).get("motor_field_in_readings") if chosen is None else None
    if in_readings:
        for a in "XYZ":
            params[f"COMPASS_MOT_{a}"] = 0.0
    if orient is not None:
        params["COMPASS_ORIENT"] = orient
    suffix = slot_suffix(cal)
    params = _named(params, suffix)
    which = "first compass" if not suffix else f"compass {int(suffix) - 1}: COMPASS_*{suffix}_"
    lines = [f"# streamcal calibration for ArduPilot ({which}), {cal.created}",
             ("# ArduPilot corrects f = S (r + COMPASS_OFS) + COMPASS_MOT * c, offsets in mG"
              " (Copter 3.6, Plane 3.9, Rover 3.3, Sub 4.0, Tracker 1.1 and later)"
              if order == MOTOR_AFTER_MATRIX else
              "# ArduPilot corrects f = S (r + COMPASS_OFS + COMPASS_MOT * c), offsets in mG"
              " (Copter 3.4-3.5, Plane 3.4-3.8, Rover 3.0-3.2, Sub 3.x, Tracker 1.0)"),
             f"# S is the symmetric (polar) form of |B| K^-1, |B| = {corr.field_uT:.6g} uT"
             + ("" if corr.field_known else " (K's mean radius: field strength unknown)"),
             "# the rotation between streamcal's and this frame is unobservable from the "
             "magnetometer alone and is not exported"]
    if chosen is not None:
        lines.append(f"# COMPASS_MOT from aux_interference on {chosen!r} "
                     f"(COMPASS_MOTCT {motct}: {'current, mG/A' if motct == 2 else 'throttle 0..1, mG'})")
        logged = (cal.extra or {}).get("ardupilot_correction_order")
        if logged and logged != order and firmware_version is None:
            lines.append(f"# the calibration comes from a log whose firmware adds COMPASS_MOT "
                         f"in the order '{logged}'; these are for '{order}': export "
                         "--firmware-version VERSION writes the order of the firmware it loads "
                         "into")
    if scale:
        lines.append(f"# COMPASS_SCALE{suffix} set to 1 (the log had {scale['value']:g}): "
                     "ArduPilot multiplies the field by it before the matrix, which here holds "
                     "the whole scale")
    if in_readings:
        lines.append(f"# COMPASS_MOT{suffix} set to 0: this calibration has no motor term, and "
                     f"was fitted on readings that carry the motor field ({in_readings} of the "
                     "log undone), so its offsets hold the field's mean; the old "
                     f"COMPASS_MOT{suffix} would remove it a second time. For a motor term refit "
                     "with --cal autopilot --add aux_interference=CHANNEL")
    if orient is not None:
        lines.append(f"# COMPASS_ORIENT{suffix} {orient}: the compass is mounted rotated "
                     f"({orientation_words(cal)}); offsets and matrix are in the "
                     "vehicle frame after that rotation (ArduPilot 4.x order)")
    lines += [f"# NOT EXPRESSED: {note}" for note in notes]
    lines += [f"{name},{fmt(value)}" for name, value in params.items()]
    return ascii_text("\n".join(lines) + "\n"), notes
