"""``mag_accel_misalignment`` (docs/effects.md): the magnetometer frame is rotated from the
accelerometer/gyro frame. A registration effect: the gravity-tied solver
(:mod:`streamcal.fitting.registration`) fits it; in a calibration file

    "mag_accel_misalignment": {"rotation": [r1, r2, r3], "dip": δ}

``rotation`` the rotation vector (rad) taking magnetometer-frame directions to the accelerometer
frame, ``dip`` δ (rad) the constant angle between the field and the "down" direction.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from .._common import number, only_keys, vector3
from ..declaration import EffectDeclaration, SimulatorTruth

NAME = "mag_accel_misalignment"


def _validate(params: Mapping) -> None:
    only_keys(params, ("rotation", "dip"), NAME)
    vector3(params, "rotation", NAME)
    number(params, "dip", NAME)


def _tied_evidence(params: Mapping, kind: str) -> str:
    if "rotation" not in params:
        return ""
    angle = np.degrees(np.linalg.norm(params["rotation"]))
    return f"; mag frame rotated {angle:.2f}° from the accel frame"


def _sim_params(rotation, env) -> dict:
    # "dip" as streamcal.fitting.registration defines it: angle between field and down (rad).
    return {"rotation": rotation.tolist(), "dip": float(np.pi / 2 - np.radians(env.dip_deg))}


EFFECT = EffectDeclaration(
    name=NAME, meaning="rotation between magnetometer and accelerometer frames",
    n_params="3 (+ dip)", kind="registration", needs=("accel",),
    units={"rotation": "rad", "dip": "rad"},
    notes={"rotation": "rotation vector, mag frame to accel frame",
           "dip": "angle between the field and down"},
    tied_evidence=_tied_evidence, validate=_validate,
    # The scenario rotates the true directions by it (x = Rᵀ x_body, R: mag → accel).
    simulated=SimulatorTruth("vector", _sim_params, magnitude="rotation angle, rad"))
