"""Registration effects (SPEC §3 ``mag_accel_misalignment``, ``time_lag``).

Parameters in a calibration file:

    "mag_accel_misalignment": {"rotation": [r1, r2, r3], "dip": δ}   rotation vector (rad) of the
        rotation R taking magnetometer-frame directions to the accelerometer frame; δ (rad) the
        constant angle between the field and the "down" direction −ĝ.
    "time_lag": {"tau": τ}     seconds by which the magnetometer samples lag the IMU clock.

They do not change how a reading maps to a magnetometer-frame direction, so ``apply`` ignores
them; they matter when the direction is combined with accel/gyro.
"""
from __future__ import annotations

from typing import Mapping

from ._common import number, only_keys, vector3


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
