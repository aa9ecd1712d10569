"""ArduPilot parameter file (``NAME,VALUE`` lines, as Mission Planner / MAVProxy load them).

ArduPilot (``AP_Compass`` backend) corrects a body-frame reading ``r`` in milligauss as
offsets → soft-iron matrix → motor compensation::

    f = S (r + COMPASS_OFS) + COMPASS_MOT · c

``S`` symmetric: diagonal COMPASS_DIA_X/Y/Z, off-diagonal COMPASS_ODI_X = S12, _Y = S13,
_Z = S23. Offsets are *added* and in mG (1 µT = 10 mG), so ``COMPASS_OFS = −10·o``.
COMPASS_MOTCT selects ``c``: 1 throttle (0..1), 2 battery current (A). Streamcal's channel term
``g·a`` in the sensor frame becomes, after the matrix, ``COMPASS_MOT = −10 · S g`` (mG per A,
or mG at full throttle). One channel only; an aux channel named ``throttle`` (0..1) maps to
MOTCT 1, ``battery_current_a`` / ``motor_current`` / ``current`` (A) to MOTCT 2.
"""
from __future__ import annotations

import re

import numpy as np

from ..calibration import Calibration
from .common import (ascii_text, correction, fmt, hold_others, joint_fit_note, motor_channel,
                     mounting, orientation_words)

MG_PER_UT = 10.0
#: COMPASS_MOTCT of each motor-compensation channel kind.
MOTCT = {"throttle": 1, "current": 2}


def apply_ardupilot(params: dict, r_mG: np.ndarray, c=None) -> np.ndarray:
    """ArduPilot's documented correction of readings ``r_mG`` (N,3) with ``params``: (N,3) mG."""
    S = np.diag([params[f"COMPASS_DIA_{a}"] for a in "XYZ"])
    S[0, 1] = S[1, 0] = params["COMPASS_ODI_X"]
    S[0, 2] = S[2, 0] = params["COMPASS_ODI_Y"]
    S[1, 2] = S[2, 1] = params["COMPASS_ODI_Z"]
    ofs = np.array([params[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    f = (np.asarray(r_mG) + ofs) @ S.T
    if c is not None and params.get("COMPASS_MOTCT", 0):
        mot = np.array([params[f"COMPASS_MOT_{a}"] for a in "XYZ"])
        f = f + np.asarray(c, dtype=float)[:, None] * mot
    return f


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
            .replace("COMPASS_ORIENT", f"COMPASS_ORIENT{suffix}"): value
            for name, value in params.items()}


def export(cal: Calibration) -> tuple[str, list[str]]:
    """(file text, notes on what ArduPilot cannot express), in the parameter names of the
    compass the calibration was fitted for."""
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
        mot = -MG_PER_UT * (S @ corr.channels[chosen])
        for k, a in enumerate("XYZ"):
            params[f"COMPASS_MOT_{a}"] = mot[k]
        params["COMPASS_MOTCT"] = motct
    if orient is not None:
        params["COMPASS_ORIENT"] = orient
    suffix = slot_suffix(cal)
    params = _named(params, suffix)
    which = "first compass" if not suffix else f"compass {int(suffix) - 1}: COMPASS_*{suffix}_"
    lines = [f"# streamcal calibration for ArduPilot ({which}), {cal.created}",
             "# ArduPilot corrects f = S (r + COMPASS_OFS) + COMPASS_MOT * c, offsets in mG",
             f"# S is the symmetric (polar) form of |B| K^-1, |B| = {corr.field_uT:.6g} uT"
             + ("" if corr.field_known else " (K's mean radius: field strength unknown)"),
             "# the rotation between streamcal's and this frame is unobservable from the "
             "magnetometer alone and is not exported"]
    if chosen is not None:
        lines.append(f"# COMPASS_MOT from aux_interference on {chosen!r} "
                     f"(COMPASS_MOTCT {motct}: {'current, mG/A' if motct == 2 else 'throttle 0..1, mG'})")
    if orient is not None:
        lines.append(f"# COMPASS_ORIENT {orient}: the compass is mounted rotated "
                     f"({orientation_words(cal)}); offsets and matrix are in the "
                     "vehicle frame after that rotation (ArduPilot 4.x order)")
    lines += [f"# NOT EXPRESSED: {note}" for note in notes]
    lines += [f"{name},{fmt(value)}" for name, value in params.items()]
    return ascii_text("\n".join(lines) + "\n"), notes
