"""The throttle ArduPilot's COMPASS_MOTCT = 1 compensation scales with, where CURR does not log
it: a copter's ``CTUN.ThO`` (0..1, 3.4 on) or ``CTUN.ThrOut`` (0..1000), a plane's ``CTUN.ThO``
/ ``ThrOut`` and a rover's ``CTUN.ThrOut`` / ``THR.ThrOut`` (percent), else the motor outputs of
``RCOU`` normalised by the PWM range (see :mod:`.dataflash`). CURR's own throttle
(:func:`curr_throttle`) is a copter's output (0..1000) but a plane's pilot input (percent).

Both take the parsed messages (``msgs.count``, ``msgs.has``, ``msgs.array``, ``msgs.params``) and
``time_of(name)`` → the message type's times (s); they return a ``throttle`` Stream (0..1) and
say in ``meta["throttle_source"]`` where it came from, or None.
"""
from __future__ import annotations

import numpy as np

from .streams import Stream

#: CURR.Throttle / ThrOut and CTUN.ThrOut run 0..1000 in the firmware versions that log them;
#: CTUN.ThO runs 0..1.
THROTTLE_FULL = 1000.0
#: A plane's CTUN.ThO / ThrOut (SRV_Channels output scaled, −100..100) and a rover's CTUN.ThrOut
#: (3.0–3.1) and THR.ThrOut (3.2 on) are in percent.
PERCENT = 100.0
#: ArduCopter's default motor PWM range (µs) when MOT_PWM_MIN/MAX are 0 or not logged.
MOTOR_PWM_US = (1000.0, 2000.0)
#: PWM outputs are 0 (off/unused) or roughly 800–2200 µs; above this is not PWM.
PWM_MAX_US = 3000.0
#: SERVOn_FUNCTION values of motors 1..8 (ArduPilot's SRV_Channel k_motor1..k_motor8).
MOTOR_FUNCTIONS = range(33, 41)
#: SERVOn_FUNCTION of a plane's throttle (k_throttle) and ArduPilot's default SERVOn_MIN/MAX.
THROTTLE_FUNCTION = 70
SERVO_PWM_US = (1100.0, 1900.0)


def is_plane(msgs) -> bool:
    """Whether the log is a plane's: its CTUN has NavRoll (ArduPlane's control message)."""
    return bool(msgs.has("CTUN", "NavRoll"))


def curr_throttle(msgs, name: str, field_name: str, meta: dict) -> np.ndarray | None:
    """CURR's ``Throttle``/``ThrOut`` as 0..1 (a copter's, 0..1000), or None where another
    message holds the throttle COMPASS_MOTCT 1 uses: a plane's CURR.Throttle (ArduPlane 3.0–3.2)
    is the pilot's throttle input (``channel_throttle->control_in``, percent), not the output,
    so its CTUN.ThrOut is taken instead (said in ``meta["curr_throttle_ignored"]``); without a
    CTUN throttle it is read as percent and said to be the pilot's input."""
    values = msgs.array(name, field_name)
    if not is_plane(msgs):
        meta["throttle_source"] = f"{name}.{field_name} / {THROTTLE_FULL:g} (0..1)"
        return values / THROTTLE_FULL
    if any(msgs.count("CTUN") and msgs.has("CTUN", f) for f in ("ThO", "ThrOut")):
        meta["curr_throttle_ignored"] = (f"{name}.{field_name}: a plane's pilot throttle input "
                                         "(percent), not its output; CTUN's taken")
        return None
    meta["throttle_source"] = (f"{name}.{field_name} / {PERCENT:g} (0..1; a plane's pilot "
                               "throttle input, logged in percent: no CTUN throttle output)")
    return values / PERCENT


def _throttle_fields(msgs) -> list[tuple[str, str, float, str]]:
    """(message, field, full scale, whose) of the throttle each vehicle logs, in the order
    tried: a plane's CTUN (its NavRoll field tells it; ThO or ThrOut, percent), a rover's CTUN
    (Steer; ThrOut, percent), a copter's CTUN (ThO 0..1, ThrOut 0..1000), a rover's THR
    (3.2 on; ThrOut, percent)."""
    if is_plane(msgs):
        ctun = [("CTUN", f, PERCENT, "a plane's") for f in ("ThO", "ThrOut")]
    elif msgs.has("CTUN", "Steer"):
        ctun = [("CTUN", "ThrOut", PERCENT, "a rover's")]
    else:
        ctun = [("CTUN", "ThO", 1.0, ""), ("CTUN", "ThrOut", THROTTLE_FULL, "")]
    return ctun + [("THR", "ThrOut", PERCENT, "a rover's")]


def ctun_throttle(msgs, time_of, meta: dict) -> Stream | None:
    """The throttle of the vehicle's control message (:func:`_throttle_fields`), as 0..1
    (a plane's or rover's reverse thrust negative)."""
    for name, field_name, full, whose in _throttle_fields(msgs):
        if msgs.count(name) and msgs.has(name, field_name):
            values = msgs.array(name, field_name) / full
            if np.all(values == values[0]):
                return None
            meta["throttle_source"] = f"{name}.{field_name}" + (
                f" / {full:g}" if full != 1.0 else "") + " (0..1" + (
                f"; {whose} throttle, logged in percent" if full == PERCENT else "") + ")"
            return Stream(name, time_of(name), {"throttle": values})
    return None


def _motor_channels(params: dict) -> tuple[list[int], str, float, float]:
    """RCOU channel numbers of the motors, where they come from and their PWM range (µs): the
    SERVOn_FUNCTION 33–40 motors over MOT_PWM_MIN/MAX; else a plane's throttle channel
    (SERVOn_FUNCTION 70) over its SERVOn_MIN/MAX; else channels 1–4 (a quadcopter)."""
    lo = float(params.get("MOT_PWM_MIN", 0) or MOTOR_PWM_US[0])
    hi = float(params.get("MOT_PWM_MAX", 0) or MOTOR_PWM_US[1])
    functions = {n: int(params.get(f"SERVO{n}_FUNCTION", -1)) for n in range(1, 33)}
    motors = [n for n, f in functions.items() if f in MOTOR_FUNCTIONS]
    if motors:
        return motors, "SERVOn_FUNCTION 33-40", lo, hi
    plane = [n for n, f in functions.items() if f == THROTTLE_FUNCTION]
    if plane:
        n = plane[0]
        return ([n], f"SERVO{n}_FUNCTION 70, throttle",
                float(params.get(f"SERVO{n}_MIN", 0) or SERVO_PWM_US[0]),
                float(params.get(f"SERVO{n}_MAX", 0) or SERVO_PWM_US[1]))
    return [1, 2, 3, 4], "channels 1-4 assumed (no SERVOn_FUNCTION logged: a quadcopter)", lo, hi


def rcou_throttle(msgs, time_of, meta: dict) -> Stream | None:
    """Mean motor output normalised by the PWM range, 0..1 (clipped)."""
    if not msgs.count("RCOU"):
        return None
    channels, origin, lo, hi = _motor_channels(msgs.params)
    names = [next((f for f in (f"C{n}", f"Ch{n}", f"Chan{n}") if msgs.has("RCOU", f)), None)
             for n in channels]
    names = [f for f in names if f is not None]
    if not names:
        return None
    pwm = np.column_stack([msgs.array("RCOU", f) for f in names])
    if hi <= lo or pwm.max() > PWM_MAX_US or np.all(pwm == pwm[0]):
        return None
    values = np.clip((pwm.mean(axis=1) - lo) / (hi - lo), 0.0, 1.0)
    meta["throttle_source"] = (f"RCOU {','.join(names)} ({origin}): mean output, "
                               f"(PWM - {lo:g}) / ({hi:g} - {lo:g}) clipped to 0..1")
    return Stream("RCOU_throttle", time_of("RCOU"), {"throttle": values})
