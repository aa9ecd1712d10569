"""Self-made autopilot logs of the vehicles streamcal has no real log of: ArduCopter 3.3–4.x,
ArduPlane 3.x/4.x and ArduRover 3.x/4.x with one to three compasses, attitude and GPS, one or two
batteries whose current runs 0–70 A, and the throttle where each firmware logs it.

The message layouts are those of each firmware's ``LogStructure`` (names, format characters and
column names; only the columns streamcal could read are filled with meaning, the others 0):

========= ============================================ ==========================================
vehicle   compasses, batteries                         throttle
========= ============================================ ==========================================
copter4   MAG with ``I``; BAT with ``Inst`` (4.1 on)   CTUN.ThO (0..1)
copter40  MAG with ``I``; BAT with ``Instance`` (4.0)  CTUN.ThO (0..1)
copter36  MAG, MAG2, MAG3; BAT, BAT2 (no instance)     CTUN.ThO (0..1)
copter34  MAG, MAG2, MAG3; CURR, CUR2 (floats)         CTUN.ThO (0..1)
copter33  MAG, MAG2, MAG3; CURR (centi-units, TimeMS)  CURR.Throttle (0..1000)
plane4    MAG with ``I``; BAT with ``Inst``            CTUN.ThO (percent, −100..100)
plane32   MAG, MAG2; CURR (centi-units)                CTUN.ThrOut (int16 percent); CURR.Throttle
                                                       the pilot's input (percent)
plane3    MAG, MAG2; BAT                               CTUN.ThrOut (int16 percent)
rover3    MAG, MAG2; BAT                               CTUN.ThrOut (int16 percent; Steer, no ThO)
rover4    MAG with ``I``; BAT with ``Inst``            THR.ThrOut (percent; no CTUN)
========= ============================================ ==========================================

The truth, per compass ``k`` in the body frame (ArduPilot logs every compass rotated into it by
COMPASS_ORIENTn): the sensor reads ``r_k = 10 (A_k e + b_k + g_k i)`` mG, ``e`` the body-frame
earth field (µT, WMM at the place and date, turned by the logged attitude), ``i`` battery 0's
current (A). The parameters in force are COMPASS_OFS{n}, DIA{n}/ODI{n}, MOT{n} with
COMPASS_MOTCT 2 (``cal``: exact unless told otherwise; a COMPASS_SCALEn among the extra
parameters multiplies ``S``), and the firmware logs
``MagX = S (r + o) + MOfs`` (or ``S (r + o + MOfs)`` before Copter 3.6 / Plane 3.9 / Rover 3.3)
with ``MOfs = MOT · i``. Like ``copter33``, ``plane32`` keeps TimeUS where its firmware logged
TimeMS, and its CURR.Throttle is the pilot's throttle input (ArduPlane 3.0–3.2 logged
``channel_throttle->control_in``, 0–100 %), here ``Flight.throttle_in``, not the output.
"""
from __future__ import annotations

import datetime
import struct
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from streamcal.geomag import ned_field, parse_date, wmm_field

LAT, LON, DATE = -35.3632, 149.1652, "2024-03-10"
GRAVITY = 9.80665
_STRUCT = {"Q": "Q", "q": "q", "I": "I", "i": "i", "H": "H", "h": "h", "B": "B", "b": "b",
           "f": "f", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "n": "4s", "N": "16s",
           "Z": "64s", "M": "b"}
_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}

#: name → (format, columns) shared by every vehicle here.
_COMMON = {
    "FMT": ("BBnNZ", "Type,Length,Name,Format,Columns"),
    "PARM": ("QNf", "TimeUS,Name,Value"),
    "MSG": ("QZ", "TimeUS,Message"),
    "ATT": ("QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
    "RCOU": ("QHHHHHHHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14"),
}
_MAG_COLS = "MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S"
_MAG_I = ("QBhhhhhhhhhBI", "TimeUS,I," + _MAG_COLS)
_MAG_OLD = ("QhhhhhhhhhBI", "TimeUS," + _MAG_COLS)
_GPS_I = ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U")
_GPS_OLD = ("QBIHBcLLefffB", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,U")
_IMU_I = ("QBffffffIIfBB", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH")
_IMU_OLD = ("QffffffIIfBB", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH")
_BAT_INST = ("QBfffffcfBBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H,SH")
_BAT_INSTANCE = ("QBfffffcf", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res")
_BAT_OLD = ("Qfffffcf", "TimeUS,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res")
_COPTER_CTUN = ("Qffffffeccfhh", "TimeUS,ThI,ABst,ThO,ThH,DAlt,Alt,BAlt,DSAlt,SAlt,TAlt,DCRt,CRt")

#: vehicle → (firmware text, layouts of its messages, how compasses are logged, batteries, the
#: throttle's message and field, the throttle's full scale in that field).
VEHICLES = {
    "copter4": ("ArduCopter V4.3.7 (self-made)", {"MAG": _MAG_I, "GPS": _GPS_I, "IMU": _IMU_I,
                "BAT": _BAT_INST, "CTUN": _COPTER_CTUN}, "I", "Inst", ("CTUN", "ThO", 1.0)),
    "copter40": ("ArduCopter V4.0.7 (self-made)", {"MAG": _MAG_I, "GPS": _GPS_I, "IMU": _IMU_I,
                 "BAT": _BAT_INSTANCE, "CTUN": _COPTER_CTUN}, "I", "Instance",
                 ("CTUN", "ThO", 1.0)),
    "copter36": ("ArduCopter V3.6.12 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
                 "MAG3": _MAG_OLD, "GPS": _GPS_OLD, "IMU": _IMU_OLD, "BAT": _BAT_OLD,
                 "BAT2": _BAT_OLD, "CTUN": _COPTER_CTUN}, "names", "BAT2", ("CTUN", "ThO", 1.0)),
    "copter34": ("APM:Copter V3.4.6 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
                 "MAG3": _MAG_OLD, "GPS": _GPS_OLD, "IMU": _IMU_OLD,
                 "CURR": ("Qfff", "TimeUS,Volt,Curr,CurrTot"),
                 "CUR2": ("Qfff", "TimeUS,Volt,Curr,CurrTot"), "CTUN": _COPTER_CTUN}, "names",
                 "CUR2", ("CTUN", "ThO", 1.0)),
    "copter33": ("APM:Copter V3.3.3 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
                 "MAG3": _MAG_OLD, "GPS": _GPS_OLD, "IMU": _IMU_OLD,
                 "CURR": ("QhhhhhfH", "TimeUS,Throttle,Volt,Curr,Vcc,CurrTot,Volt2,Flags")},
                 "names", None, ("CURR", "Throttle", 1000.0)),
    "plane4": ("ArduPlane V4.3.5 (self-made)", {"MAG": _MAG_I, "GPS": _GPS_I, "IMU": _IMU_I,
               "BAT": _BAT_INST, "CTUN": ("QccccffffBffi", "TimeUS,NavRoll,Roll,NavPitch,Pitch,"
                                                            "ThO,RdO,ThD,As,AsT,SAs,E2T,GU")},
               "I", "Inst", ("CTUN", "ThO", 100.0)),
    "plane32": ("ArduPlane V3.2.3 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
                "GPS": _GPS_OLD, "IMU": _IMU_OLD,
                "CURR": ("Qhhhhf", "TimeUS,Throttle,Volt,Curr,Vcc,CurrTot"),
                "CTUN": ("Qcccchhf", "TimeUS,NavRoll,Roll,NavPitch,Pitch,ThrOut,RdrOut,AccY")},
                "names", None, ("CTUN", "ThrOut", 100.0)),
    "plane3": ("ArduPlane V3.9.11 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
               "GPS": _GPS_OLD, "IMU": _IMU_OLD, "BAT": _BAT_OLD,
               "CTUN": ("Qccccchhf", "TimeUS,NavRoll,Roll,NavPitch,Pitch,ThrOut,RdrOut,ThrDem,"
                                     "Aspd")}, "names", None, ("CTUN", "ThrOut", 100.0)),
    "rover3": ("APM:Rover v3.1.2 (self-made)", {"MAG": _MAG_OLD, "MAG2": _MAG_OLD,
               "GPS": _GPS_OLD, "IMU": _IMU_OLD, "BAT": _BAT_OLD,
               "CTUN": ("Qhcchf", "TimeUS,Steer,Roll,Pitch,ThrOut,AccY")}, "names", None,
               ("CTUN", "ThrOut", 100.0)),
    "rover4": ("ArduRover V4.2.3 (self-made)", {"MAG": _MAG_I, "GPS": _GPS_I, "IMU": _IMU_I,
               "BAT": _BAT_INST, "THR": ("Qhffff", "TimeUS,ThrIn,ThrOut,DesSpeed,Speed,AccY")},
               "I", "Inst", ("THR", "ThrOut", 100.0)),
}


@dataclass
class Compass:
    """One compass's truth (body frame): soft iron ``A`` (3,3), hard iron ``b`` µT, current
    term ``g`` µT/A; the parameters in force are exact unless ``ofs_error`` (mG, added to
    COMPASS_OFS) or ``mot_in_force`` (mG/A, instead of the exact COMPASS_MOT) say otherwise."""

    A: np.ndarray = field(default_factory=lambda: np.eye(3))
    b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ofs_error: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mot_in_force: np.ndarray | None = None
    dev_id: int = 0
    #: (3,3) sensor → body rotation of a compass mounted turned while COMPASS_ORIENTn says 0:
    #: it reads ``mountᵀ r`` and the parameters in force are those of that frame
    mount: np.ndarray = field(default_factory=lambda: np.eye(3))

    def S(self) -> np.ndarray:
        return np.linalg.inv(self.A)

    def params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(S, COMPASS_OFS mG, COMPASS_MOT mG/A) in force, in the frame the compass reads."""
        M = np.asarray(self.mount, float)
        S = M.T @ self.S() @ M
        ofs = -10.0 * M.T @ np.asarray(self.b, float) + self.ofs_error
        mot = -10.0 * S @ M.T @ np.asarray(self.g, float) if self.mot_in_force is None \
            else np.asarray(self.mot_in_force, float)
        return S, ofs, mot


def _pack(fmt: str, values) -> bytes:
    out = []
    for ch, v in zip(fmt, values):
        if ch in _SCALE:
            v = int(round(float(v) * _SCALE[ch]))
        elif ch in "QqIiHhBbM":
            v = int(round(float(v)))
        elif ch in "nNZ" and isinstance(v, str):
            v = v.encode()
        out.append(v)
    return struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *out)


@dataclass
class Flight:
    """The truth of a written log: times ``t`` (n,) s, ``current`` (n,) A of battery 0,
    ``current2`` (n,) A, ``throttle`` (n,) 0..1, ``e`` (n,3) body-frame earth field µT,
    ``logged`` {compass: (n,3) MagX/Y/Z mG}, ``accel`` (n,3) m/s², ``compasses``, ``b_ned``."""

    t: np.ndarray
    current: np.ndarray
    current2: np.ndarray
    throttle: np.ndarray
    e: np.ndarray
    logged: dict
    accel: np.ndarray
    compasses: list
    b_ned: np.ndarray
    vehicle: str = ""
    #: (n,) 0..1: the pilot's throttle input (plane32's CURR.Throttle), unlike ``throttle``
    throttle_in: np.ndarray | None = None


def flight_profile(seconds: float, seed: int, rate_hz: float = 10.0, tilt_deg: float = 25.0):
    """(t, attitude Rotation body→NED, battery 0 current 0..70 A, battery 2 current A, throttle
    0..1): two turns through every heading, roll/pitch wander ±tilt, current swings 0–70 A."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t = np.arange(n) / rate_hz
    yaw = 720.0 * t / seconds + 15.0 * np.sin(2 * np.pi * t / 17.0)
    roll = tilt_deg * np.sin(2 * np.pi * t / 9.3 + 0.4)
    pitch = tilt_deg * 0.8 * np.sin(2 * np.pi * t / 13.1 + 1.1)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    current = np.clip(35.0 - 35.0 * np.cos(2 * np.pi * t / 23.0) + rng.normal(0, 1.0, n), 0, 70)
    current2 = 8.0 + 6.0 * np.sin(2 * np.pi * t / 7.7) ** 2
    throttle = np.clip(0.15 + 0.75 * (current / 70.0) ** 0.7 + 0.04 * np.sin(2 * np.pi * t / 3.3),
                       0, 1)
    return t, att, current, current2, throttle


def write_vehicle_log(path, vehicle: str, compasses: list[Compass], *, seconds: float = 120.0,
                      seed: int = 0, noise_mG: float = 2.0, extra_params=None,
                      two_batteries: bool = False, motct: int = 2,
                      second_volts=lambda t: 15.1) -> Flight:
    """Write ``vehicle``'s log (:data:`VEHICLES`) of ``compasses`` to ``path``; the truth.
    ``second_volts(t)`` is the second battery's voltage (V) at time ``t`` s."""
    firmware, layouts, mag_kind, bat2, (thr_msg, thr_field, thr_full) = VEHICLES[vehicle]
    layouts = {**_COMMON, **layouts}
    if mag_kind == "names":
        layouts = {k: v for k, v in layouts.items()
                   if k not in ("MAG", "MAG2", "MAG3")[len(compasses):]}
    rng = np.random.default_rng(seed + 7)
    t, att, current, current2, throttle = flight_profile(seconds, seed)
    b_ned = ned_field(wmm_field(LAT, LON, 0.58, parse_date(DATE)))
    e = att.inv().apply(b_ned)
    accel = att.inv().apply([0.0, 0.0, -GRAVITY])
    gyro = np.zeros_like(accel)
    ids = {name: 128 - 40 + k for k, name in enumerate(layouts) if name != "FMT"}
    ids["FMT"] = 128
    out = []
    for name, (fmt, cols) in layouts.items():
        size = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
        out.append(b"\xa3\x95\x80" + _pack("BBnNZ", (ids[name], size, name, fmt, cols)))

    def msg(name, *values):
        out.append(b"\xa3\x95" + bytes([ids[name]]) + _pack(layouts[name][0], values))

    us0 = 3_000_000
    msg("MSG", us0, firmware)
    params = {"COMPASS_MOTCT": motct, "AHRS_ORIENTATION": 0}
    for k, c in enumerate(compasses):
        sfx, ext = ("", "EXTERNAL") if k == 0 else (str(k + 1), f"EXTERN{k + 1}")
        S, ofs, mot = c.params()
        for a, v in zip("XYZ", ofs):
            params[f"COMPASS_OFS{sfx}_{a}"] = v
        for a, v in zip("XYZ", np.diag(S)):
            params[f"COMPASS_DIA{sfx}_{a}"] = v
        for a, v in zip("XYZ", (S[0, 1], S[0, 2], S[1, 2])):
            params[f"COMPASS_ODI{sfx}_{a}"] = v
        for a, v in zip("XYZ", mot):
            params[f"COMPASS_MOT{sfx}_{a}"] = v
        params[f"COMPASS_DEV_ID{sfx}"] = c.dev_id or 97539 + 256 * k
        params[f"COMPASS_ORIENT{sfx}"] = 0
        params[f"COMPASS_{ext}"] = 1 if k == 0 else 0
        params[f"COMPASS_USE{sfx}"] = 1
    params.update(extra_params or {})
    for name, value in params.items():
        msg("PARM", us0, name, float(value))
    before = vehicle in ("copter33", "copter34", "rover3", "plane32")   # Copter < 3.6,
    # Rover < 3.3, Plane < 3.9
    throttle_in = np.clip(0.8 * throttle + 0.15, 0.0, 1.0)
    logged = {}
    for k, c in enumerate(compasses):
        S, ofs, mot = c.params()
        S = S * (params.get(f"COMPASS_SCALE{'' if k == 0 else k + 1}", 0.0) or 1.0)
        raw = (10.0 * (e @ np.asarray(c.A, float).T + c.b + np.outer(current, c.g))) \
            @ np.asarray(c.mount, float) + rng.normal(0.0, noise_mG, e.shape)
        mofs = np.outer(current if motct == 2 else throttle, mot)
        logged[k] = np.round((raw + ofs + mofs) @ S.T if before else (raw + ofs) @ S.T + mofs)
        c._mofs, c._ofs = np.round(mofs), np.round(ofs)
    day = datetime.datetime.fromisoformat(DATE).replace(tzinfo=datetime.timezone.utc)
    gps_s = (day - datetime.datetime(1980, 1, 6, tzinfo=datetime.timezone.utc)).total_seconds()
    euler = att.as_euler("ZYX", degrees=True)
    inst = bat2 if bat2 in ("Inst", "Instance") else None
    for i, ti in enumerate(t):
        us = us0 + int(round(ti * 1e6))
        imu = [us] + ([0] if "I" in layouts["IMU"][1].split(",")[1:2] else []) + \
            [*gyro[i], *accel[i], 0, 0, 0.0, 1, 1]
        msg("IMU", *imu)
        msg("ATT", us, 0, euler[i, 2], 0, euler[i, 1], 0, euler[i, 0] % 360.0, 0, 0)
        for k, c in enumerate(compasses):
            row = [*logged[k][i], *c._ofs, *c._mofs[i], 1, us - 500]
            if mag_kind == "I":
                msg("MAG", us, k, *row)
            else:
                msg(("MAG", "MAG2", "MAG3")[k], us, *row)
        volt = 16.4 - 0.01 * ti - 0.01 * current[i]
        if "BAT" in layouts:
            if inst:
                msg("BAT", us, 0, volt, volt, current[i], 0, 0, 25, 0.02,
                    *([80, 1, 100] if inst == "Inst" else []))
                if two_batteries:
                    msg("BAT", us, 1, second_volts(ti), 15.1, current2[i], 0, 0, 25, 0.02,
                        *([80, 1, 100] if inst == "Inst" else []))
            else:
                msg("BAT", us, volt, volt, current[i], 0, 0, 25, 0.02)
                if two_batteries and "BAT2" in layouts:
                    msg("BAT2", us, second_volts(ti), 15.1, current2[i], 0, 0, 25, 0.02)
        if "CUR2" in layouts:
            msg("CURR", us, volt, current[i], 0)
            if two_batteries:
                msg("CUR2", us, second_volts(ti), current2[i], 0)
        elif "CURR" in layouts and vehicle == "plane32":
            msg("CURR", us, throttle_in[i] * 100, volt * 100, current[i] * 100, 5000, 0)
        elif "CURR" in layouts:
            msg("CURR", us, throttle[i] * 1000, volt * 100, current[i] * 100, 5000, 0, 0, 0)
        thr_values = {name: 0 for name in layouts[thr_msg][1].split(",")}
        thr_values["TimeUS"] = us
        thr_values[thr_field] = throttle[i] * thr_full
        if thr_msg != "CURR":
            msg(thr_msg, *thr_values.values())
        pwm = 1000 + 1000 * throttle[i]
        msg("RCOU", us, *([pwm] * 4 if vehicle.startswith("copter") else
                          [1500, 1500, pwm, 1500]), *([0] * 10))
        if i % 5 == 0:
            gms = (gps_s + 12 * 3600 + ti) % (7 * 86400) * 1000.0
            week = int((gps_s + 12 * 3600 + ti) // (7 * 86400))
            row = [3, gms, week, 12, 0.8, LAT, LON, 580.0, 0, 0, 0]
            msg("GPS", us, *([0] if mag_kind == "I" else []), *row,
                *([0, 1] if mag_kind == "I" else [1]))
    with open(path, "wb") as fh:
        fh.write(b"".join(out))
    return Flight(t, current, current2, throttle, e, logged, accel, compasses, b_ned, vehicle,
                  throttle_in)


def soft_iron(seed: int, size: float = 0.05) -> np.ndarray:
    """A symmetric soft-iron matrix near the identity."""
    rng = np.random.default_rng(seed)
    M = rng.normal(0.0, size, (3, 3))
    return np.eye(3) + (M + M.T) / 2
