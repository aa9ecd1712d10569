"""Parameters of the registration effects (``mag_accel_misalignment``, ``time_lag``) in a
calibration file; their solver is :mod:`streamcal.fitting.registration`.

    "mag_accel_misalignment": {"rotation": [r1, r2, r3], "dip": δ}   rotation vector (rad) of the
        rotation taking magnetometer-frame directions to the accelerometer frame; δ (rad) the
        constant angle between the field and the "down" direction.
    "time_lag": {"tau": τ}     seconds by which the magnetometer samples lag the IMU clock.
"""
from __future__ import annotations

from typing import Mapping

from ._common import number, only_keys, vector3

NAMES = ("mag_accel_misalignment", "time_lag")


def validate_registration_params(name: str, params: Mapping) -> None:
    """ValueError naming the effect and key when ``params`` is malformed."""
    if name == "mag_accel_misalignment":
        only_keys(params, ("rotation", "dip"), name)
        vector3(params, "rotation", name)
        number(params, "dip", name)
    elif name == "time_lag":
        only_keys(params, ("tau",), name)
        number(params, "tau", name)
    else:
        raise ValueError(f"{name!r} is not a registration effect")


# ---------------------------------------------------------------------------------- gravity
