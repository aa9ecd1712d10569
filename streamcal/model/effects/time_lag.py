"""``time_lag`` (docs/effects.md): the magnetometer samples lag the IMU clock. A registration
effect: the gravity-tied solver (:mod:`streamcal.fitting.registration`), or the gyro-tied one
(:mod:`streamcal.fitting.gyro_lag`) on a track without an accelerometer, fits it; in a
calibration file

    "time_lag": {"tau": τ}     seconds by which the magnetometer samples lag the IMU clock.
"""
from __future__ import annotations

from typing import Mapping

from .._common import number, only_keys
from ..declaration import EffectDeclaration, SimulatorTruth

NAME = "time_lag"


def _validate(params: Mapping) -> None:
    only_keys(params, ("tau",), NAME)
    number(params, "tau", NAME)


def _tied_evidence(params: Mapping, kind: str) -> str:
    if "tau" not in params:
        return ""
    tau_ms = 1e3 * params["tau"]
    if kind == "gyro":
        return (f"; direction changes {'lag' if tau_ms >= 0 else 'lead'} the gyro by "
                f"{abs(tau_ms):.1f} ms")
    return f"; mag lags the IMU by {tau_ms:.1f} ms"


EFFECT = EffectDeclaration(
    name=NAME, meaning="magnetometer samples lag the IMU clock", n_params="1",
    kind="registration", needs_any=("gyro", "accel"),
    units={"tau": "s"},
    tied_evidence=_tied_evidence, validate=_validate,
    # The scenario samples the magnetometer at t − τ and stamps it t.
    simulated=SimulatorTruth("scalar", lambda tau, env: {"tau": float(tau)},
                             magnitude="τ, s", limit=0.5, limit_unit="s"))
