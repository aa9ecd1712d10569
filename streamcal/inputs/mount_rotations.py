"""The sensor mounting rotations autopilots know by number: ArduPilot's ``Rotation`` enum
(``AP_Math/rotations.h``, parameter COMPASS_ORIENTn) and PX4's (``conversion/rotation.h``,
CAL_MAGn_ROT), restricted to 90° steps and 45° yaws.

Both enums number these rotations alike from 0 (NONE) to 37 (ROLL_90_YAW_270); each is the
Euler rotation ``R = Rz(yaw) Ry(pitch) Rx(roll)`` and the autopilot turns a sensor reading
into the vehicle (body) frame as ``body = R · sensor``. Past 37 the two enums differ: PX4 adds
more 90°-step rotations (41 ROLL_270_YAW_180, 42 ROLL_270_YAW_270, 43 PITCH_90_YAW_180,
46 ROLL_270_YAW_225, 47 ROLL_270_YAW_315) that ArduPilot numbers otherwise or not at all, so
those carry the ArduPilot number of the same matrix when there is one, else None. Several
names are the same matrix (ArduPilot 26 PITCH_180_YAW_90 = 14 ROLL_180_YAW_270…); the first
number is kept.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class MountRotation:
    """One named rotation: ``name`` (as the enums spell it without ``ROTATION_``), its
    ``ardupilot`` and ``px4`` numbers (None where that autopilot has none) and ``matrix``
    (3,3) taking sensor-frame vectors to the body frame."""

    name: str
    ardupilot: int | None
    px4: int | None
    matrix: np.ndarray


#: (number, name, roll, pitch, yaw in degrees), numbers shared by ArduPilot and PX4.
_SHARED = (
    (0, "NONE", 0, 0, 0), (1, "YAW_45", 0, 0, 45), (2, "YAW_90", 0, 0, 90),
    (3, "YAW_135", 0, 0, 135), (4, "YAW_180", 0, 0, 180), (5, "YAW_225", 0, 0, 225),
    (6, "YAW_270", 0, 0, 270), (7, "YAW_315", 0, 0, 315), (8, "ROLL_180", 180, 0, 0),
    (9, "ROLL_180_YAW_45", 180, 0, 45), (10, "ROLL_180_YAW_90", 180, 0, 90),
    (11, "ROLL_180_YAW_135", 180, 0, 135), (12, "PITCH_180", 0, 180, 0),
    (13, "ROLL_180_YAW_225", 180, 0, 225), (14, "ROLL_180_YAW_270", 180, 0, 270),
    (15, "ROLL_180_YAW_315", 180, 0, 315), (16, "ROLL_90", 90, 0, 0),
    (17, "ROLL_90_YAW_45", 90, 0, 45), (18, "ROLL_90_YAW_90", 90, 0, 90),
    (19, "ROLL_90_YAW_135", 90, 0, 135), (20, "ROLL_270", 270, 0, 0),
    (21, "ROLL_270_YAW_45", 270, 0, 45), (22, "ROLL_270_YAW_90", 270, 0, 90),
    (23, "ROLL_270_YAW_135", 270, 0, 135), (24, "PITCH_90", 0, 90, 0),
    (25, "PITCH_270", 0, 270, 0), (26, "PITCH_180_YAW_90", 0, 180, 90),
    (27, "PITCH_180_YAW_270", 0, 180, 270), (28, "ROLL_90_PITCH_90", 90, 90, 0),
    (29, "ROLL_180_PITCH_90", 180, 90, 0), (30, "ROLL_270_PITCH_90", 270, 90, 0),
    (31, "ROLL_90_PITCH_180", 90, 180, 0), (32, "ROLL_270_PITCH_180", 270, 180, 0),
    (33, "ROLL_90_PITCH_270", 90, 270, 0), (34, "ROLL_180_PITCH_270", 180, 270, 0),
    (35, "ROLL_270_PITCH_270", 270, 270, 0), (36, "ROLL_90_PITCH_180_YAW_90", 90, 180, 90),
    (37, "ROLL_90_YAW_270", 90, 0, 270),
)
#: PX4-only numbers of 90°/45°-yaw rotations.
_PX4_ONLY = ((41, "ROLL_270_YAW_180", 270, 0, 180), (42, "ROLL_270_YAW_270", 270, 0, 270),
             (43, "PITCH_90_YAW_180", 0, 90, 180), (46, "ROLL_270_YAW_225", 270, 0, 225),
             (47, "ROLL_270_YAW_315", 270, 0, 315))


def euler_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (degrees), entries rounded to the exact 0, ±½√2, ±1."""
    m = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
    return np.round(m, 12) + 0.0


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a, b, atol=1e-6))


@lru_cache(maxsize=1)
def mount_rotations() -> tuple[MountRotation, ...]:
    """Every distinct rotation of the table, NONE first (duplicates merged)."""
    out: list[MountRotation] = []
    for number, name, r, p, y in _SHARED:
        m = euler_matrix(r, p, y)
        if not any(_same(m, o.matrix) for o in out):
            out.append(MountRotation(name, number, number, m))
    for number, name, r, p, y in _PX4_ONLY:
        m = euler_matrix(r, p, y)
        twin = next((o for o in out if _same(m, o.matrix)), None)
        if twin is None:
            out.append(MountRotation(name, None, number, m))
    for rot in out:
        rot.matrix.flags.writeable = False
    return tuple(out)


def by_name(name: str) -> MountRotation:
    """The rotation called ``name`` (``YAW_90``…); KeyError when the table has none."""
    for rot in mount_rotations():
        if rot.name == name.upper().removeprefix("ROTATION_"):
            return rot
    raise KeyError(name)


def as_dict(rot: MountRotation, angle_error_deg: float | None) -> dict:
    """The ``orientation`` object of the JSON outputs (docs/flight_logs.md)."""
    return {"name": rot.name, "ardupilot": rot.ardupilot, "px4": rot.px4,
            "angle_error_deg": None if angle_error_deg is None else round(float(angle_error_deg), 2)}


def by_number(number: int, firmware: str = "ardupilot") -> MountRotation | None:
    """The table's rotation that ``firmware`` (``"ardupilot"``/``"px4"``) calls ``number``
    (ArduPilot's duplicates 26 and 27 give the entry with their matrix); None for a number
    outside the 90°/45°-yaw set."""
    rows = _SHARED + (_PX4_ONLY if firmware == "px4" else ())
    for n, _, r, p, y in rows:
        if n == number:
            return matching(euler_matrix(r, p, y))
    return None


def matching(matrix: np.ndarray) -> MountRotation | None:
    """The table's rotation with this matrix (3,3), None when there is none."""
    for rot in mount_rotations():
        if _same(rot.matrix, np.asarray(matrix, float)):
            return rot
    return None
