"""PX4 parameters for the first magnetometer (``CAL_MAG0_*``), as a QGroundControl ``.params``
file (tab-separated ``vehicle-id  component-id  name  value  type``).

PX4 (``sensors`` Magnetometer calibration) corrects a reading ``r`` in gauss as
``f = R · S · (r − o)``: ``o`` = CAL_MAG0_XOFF/YOFF/ZOFF (G, *subtracted*), ``S`` symmetric with
diagonal CAL_MAG0_XSCALE/YSCALE/ZSCALE and off-diagonal CAL_MAG0_XODIAG = S12, YODIAG = S13,
ZODIAG = S23; ``R`` the board or CAL_MAG0_ROT rotation (left as is). 1 G = 100 µT.
Power compensation (CAL_MAG0_XCOMP..) is not written: its scaling is not exported by streamcal
and any aux_interference term is said to be not expressed.
"""
from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from .common import correction, fmt

UT_PER_GAUSS = 100.0
FLOAT_TYPE = 9  # MAV_PARAM_TYPE_REAL32


def apply_px4(params: dict, r_gauss: np.ndarray) -> np.ndarray:
    """PX4's documented correction (without the rotation) of readings (N,3) G: (N,3) G."""
    S = np.diag([params[f"CAL_MAG0_{a}SCALE"] for a in "XYZ"])
    S[0, 1] = S[1, 0] = params["CAL_MAG0_XODIAG"]
    S[0, 2] = S[2, 0] = params["CAL_MAG0_YODIAG"]
    S[1, 2] = S[2, 1] = params["CAL_MAG0_ZODIAG"]
    off = np.array([params[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    return (np.asarray(r_gauss) - off) @ S.T


def export(cal: Calibration) -> tuple[str, list[str]]:
    corr = correction(cal)
    S, notes = corr.S, list(corr.not_expressed)
    notes += [f"aux_interference on {name!r}: PX4 power compensation (CAL_MAG0_*COMP) is not "
              "exported" for name in corr.channels]
    params = {}
    for k, a in enumerate("XYZ"):
        params[f"CAL_MAG0_{a}OFF"] = corr.offset[k] / UT_PER_GAUSS
    for k, a in enumerate("XYZ"):
        params[f"CAL_MAG0_{a}SCALE"] = S[k, k]
    params["CAL_MAG0_XODIAG"], params["CAL_MAG0_YODIAG"], params["CAL_MAG0_ZODIAG"] = \
        S[0, 1], S[0, 2], S[1, 2]
    lines = [f"# streamcal calibration for PX4 (CAL_MAG0), {cal.created}",
             "# PX4 corrects f = R S (r - CAL_MAG0_OFF), offsets in gauss; CAL_MAG0_ID and _ROT "
             "are left as they are on the vehicle",
             f"# S is the symmetric (polar) form of |B| K^-1, |B| = {corr.field_uT:.6g} uT"
             + ("" if corr.field_known else " (K's mean radius: field strength unknown)"),
             "# the rotation between streamcal's and this frame is unobservable from the "
             "magnetometer alone and is not exported",
             "# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    lines += [f"# NOT EXPRESSED: {note}" for note in notes]
    lines += [f"1\t1\t{name}\t{fmt(value)}\t{FLOAT_TYPE}" for name, value in params.items()]
    return "\n".join(lines) + "\n", notes
