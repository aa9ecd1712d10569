"""Self-made ArduPilot DataFlash logs with one to three compasses, a known truth, for tests.

Bytes as ArduPilot writes them (and pymavlink's DFReader reads them): each message is
``0xA3 0x95 type`` + the little-endian payload its FMT message declares; FMT (type 128, 89 bytes)
describes every type before its first message.

The vehicle tumbles (smooth random body rates) in an Earth field of 500 mG, dip 60°. Compass
``k`` reads ``raw = f + err_k − ofs_k − mot·throttle`` (mG): ``f`` the body-frame field,
``err_k`` a hard iron its calibration in force (``COMPASSn_OFS = ofs_k``) does not remove; the
autopilot logs ``MagX = raw + ofs_k + MOfs`` with ``MOfs = mot·throttle`` (COMPASS_MOT, MOTCT=1),
so the logged field is ``f + err_k`` plus noise.
"""
from __future__ import annotations

import struct

import numpy as np
from scipy.spatial.transform import Rotation

FIELD_MG, DIP_DEG, G = 500.0, 60.0, 9.80665
EARTH_NED = FIELD_MG * np.array([np.cos(np.radians(DIP_DEG)), 0.0, np.sin(np.radians(DIP_DEG))])
_CHARS = {"Q": "Q", "B": "B", "h": "h", "f": "f", "N": "16s", "I": "I"}
_TYPES = {"PARM": 64, "MAG": 10, "MAG2": 11, "MAG3": 12, "IMU": 20, "CTUN": 30, "RCOU": 40}


def _fmt_message(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = 3 + struct.calcsize("<" + "".join(_CHARS[c] for c in fmt))
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name.encode(),
                                          fmt.encode(), columns.encode())


def _message(type_id: int, fmt: str, values) -> bytes:
    return bytes([0xA3, 0x95, type_id]) + struct.pack(
        "<" + "".join(_CHARS[c] for c in fmt), *values)


def tumble(seconds: float, rate_hz: float, seed: int):
    """``(t (n,), Rotation body→NED (n,), body rates (n,3) rad/s)`` of a smooth random tumble."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    knots = rng.normal(0.0, 1.6, (int(seconds) + 2, 3))
    rates = np.column_stack([np.interp(t, np.arange(len(knots)), knots[:, k]) for k in range(3)])
    steps = Rotation.from_rotvec(rates / rate_hz)
    rot = [Rotation.random(random_state=rng)]
    for s in steps[:-1]:
        rot.append(rot[-1] * s)
    return t, Rotation.concatenate(rot), rates


def write_flight(path, compasses, *, seconds: float = 90.0, seed: int = 0, layout: str = "old",
                 motct: int = 0, mot=(0.0, 0.0, 0.0), throttle_in: str = "CTUN",
                 noise_mG: float = 3.0, extra_params=None) -> dict:
    """Write a log; ``compasses`` a list of ``{"ofs": (3,), "err": (3,)}`` mG (defaults 0).

    ``layout``: ``"old"`` (MAG, MAG2, MAG3) or ``"instance"`` (MAG with an ``I`` field).
    ``throttle_in``: ``"CTUN"`` (CTUN.ThO 0..1), ``"RCOU"`` (motor PWM C1..C4 only) or ``""``.
    Returns the truth: ``t`` s, ``throttle``, ``field`` (n,3) body mG at the MAG instants.
    """
    rng = np.random.default_rng(seed + 100)
    t, rot, rates = tumble(seconds, 50.0, seed)
    t_us = (t * 1e6).astype(np.int64) + 1_000_000
    f_body = rot.inv().apply(EARTH_NED)
    accel = rot.inv().apply([0.0, 0.0, -G])
    throttle = 0.45 + 0.3 * np.sin(2 * np.pi * t / 11.0) + 0.1 * np.sin(2 * np.pi * t / 3.1)
    mot = np.asarray(mot, float)
    out = []
    fmts = {"PARM": ("QNf", "TimeUS,Name,Value"), "IMU": ("Qffffff", "TimeUS,GyrX,GyrY,GyrZ,"
                                                          "AccX,AccY,AccZ"),
            "CTUN": ("Qff", "TimeUS,ThI,ThO"), "RCOU": ("Qhhhh", "TimeUS,C1,C2,C3,C4")}
    mag_cols = "MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"
    if layout == "instance":
        fmts["MAG"] = ("QBhhhhhhhhh", "TimeUS,I," + mag_cols)
    else:
        for k in range(len(compasses)):
            fmts[("MAG", "MAG2", "MAG3")[k]] = ("Qhhhhhhhhh", "TimeUS," + mag_cols)
    for name, (fmt, cols) in fmts.items():
        out.append(_fmt_message(_TYPES[name], name, fmt, cols))
    params = {"COMPASS_MOTCT": motct}
    for k, c in enumerate(compasses):
        sfx = "" if k == 0 else str(k + 1)
        for a, v in zip("XYZ", c.get("ofs", (0, 0, 0))):
            params[f"COMPASS_OFS{sfx}_{a}"] = v
        for a, v in zip("XYZ", mot):
            params[f"COMPASS_MOT{sfx}_{a}"] = v
        params[f"COMPASS_DEV_ID{sfx}"] = 97539 + 256 * k
    params.update(extra_params or {})
    for name, value in params.items():
        out.append(_message(_TYPES["PARM"], "QNf", (t_us[0], name.encode(), float(value))))
    for i in range(len(t)):
        out.append(_message(_TYPES["IMU"], "Qffffff", (t_us[i], *rates[i], *accel[i])))
        if i % 5:
            continue    # MAG, CTUN and RCOU at 10 Hz
        if throttle_in == "CTUN":
            out.append(_message(_TYPES["CTUN"], "Qff", (t_us[i], throttle[i], throttle[i])))
        if throttle_in == "RCOU":
            pwm = int(round(1000 + 1000 * throttle[i]))
            out.append(_message(_TYPES["RCOU"], "Qhhhh", (t_us[i], pwm, pwm, pwm, pwm)))
        mofs = mot * throttle[i]
        for k, c in enumerate(compasses):
            ofs = np.asarray(c.get("ofs", (0, 0, 0)), float)
            logged = f_body[i] + np.asarray(c.get("err", (0, 0, 0)), float) \
                + rng.normal(0.0, noise_mG, 3)
            values = [int(round(v)) for v in (*logged, *ofs, *mofs)]
            if layout == "instance":
                out.append(_message(_TYPES["MAG"], "QBhhhhhhhhh", (t_us[i], k, *values)))
            else:
                name = ("MAG", "MAG2", "MAG3")[k]
                out.append(_message(_TYPES[name], "Qhhhhhhhhh", (t_us[i], *values)))
    with open(path, "wb") as fh:
        fh.write(b"".join(out))
    return {"t": t[::5], "throttle": throttle[::5], "field": f_body[::5]}
