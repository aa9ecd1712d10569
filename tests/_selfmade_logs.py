"""Self-made autopilot logs for the tests that must not need the real recordings.

:func:`flight_slice` simulates a drone-like slice (yaw turns, small tilts, a gyro) with throttle,
six PWM outputs and a battery, and optionally a motor field proportional to the throttle (or to one
motor output) hidden in the magnetometer. :func:`write_dataflash` writes it as an ArduPilot
DataFlash ``.bin`` as the firmware logs it (the *corrected* field ``S (raw + o) + MOfs`` in mG,
COMPASS_* parameters); :func:`write_ulog` as a PX4 ``.ulg`` (``sensor_mag`` raw or
``vehicle_magnetometer`` corrected ``S (r − o)`` in gauss, CAL_MAG0_* parameters). Both follow the
public file formats (DataFlash: ``0xA3 0x95`` headers, FMT messages; ULog: the 16-byte header, then
B/F/I/P/A/D messages).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from streamcal.sim.yaw_slice import yaw_slice

#: The true sensor (µT): a symmetric soft iron (so ArduPilot's and PX4's symmetric matrices can
#: express it exactly) and a hard iron whose ×10 (mG) and /100 (G) are exact.
A_TRUE = 48.0 * np.array([[1.04, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 1.01]])
B_TRUE = np.array([12.0, -7.0, 20.0])
FIELD_UT = 48.0
#: The hidden motor field's direction (unit) and size at full throttle (µT).
MOTOR_DIRECTION = np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])
FIRMWARE = "ArduCopter V4.0.7 (self-made test log)"


@dataclass
class FlightSlice:
    """Body-frame readings and channels of a simulated flight; times in s from 0."""

    t_mag: np.ndarray            # (N,)
    mag_uT: np.ndarray           # (N, 3) what the sensor reads (motor field included)
    t_imu: np.ndarray            # (M,)
    accel: np.ndarray            # (M, 3) m/s²
    gyro: np.ndarray             # (M, 3) rad/s
    temp: np.ndarray             # (M,) °C
    throttle_at_mag: np.ndarray  # (N,) 0..1, the throttle at each mag sample
    t_ch: np.ndarray             # (P,) stamps of the channel messages (RCOU, CURR, BAT)
    throttle: np.ndarray         # (P,) 0..1
    pwm: np.ndarray              # (P, 6) µs
    volts: np.ndarray            # (P,) V
    amps: np.ndarray             # (P,) A
    motor_uT: float = 0.0
    extra: dict = field(default_factory=dict)


def _throttle(t: np.ndarray) -> np.ndarray:
    """A smooth hover throttle with climbs: 0.35..0.85, slow enough to follow at 10 Hz."""
    return 0.6 + 0.2 * np.sin(2 * np.pi * t / 13.0) + 0.05 * np.sin(2 * np.pi * t / 3.1)


#: Periods (s) of each motor's own correction about the common throttle (a quad's attitude
#: control), so that the five driven outputs are not copies of the throttle or of each other.
_MOTOR_PERIODS = (7.3, 5.1, 9.7, 4.3, 11.9)


def _pwm(t: np.ndarray) -> np.ndarray:
    """(len(t), 6) PWM outputs in µs: five motors about 1100 + 800 × throttle, a servo at rest."""
    motors = [1100.0 + 800.0 * _throttle(t) + 90.0 * np.sin(2 * np.pi * t / p + k)
              for k, p in enumerate(_MOTOR_PERIODS)]
    return np.column_stack(motors + [np.full(len(t), 1500.0)])


def _volts(t: np.ndarray, throttle: np.ndarray) -> np.ndarray:
    """Battery voltage (V): a slow discharge and a sag under load."""
    return 12.6 - 0.01 * t - 0.6 * throttle ** 2


def _amps(t: np.ndarray, throttle: np.ndarray) -> np.ndarray:
    """Battery current (A): rising faster than the throttle, plus the attitude corrections."""
    return 1.5 + 28.0 * throttle ** 1.5 + 2.0 * np.sin(2 * np.pi * t / 6.7)


def flight_slice(duration_s: float = 60.0, seed: int = 0, *, motor_uT: float = 0.0,
                 motor_channel: str = "throttle", tilt_deg: float = 12.0) -> FlightSlice:
    """A yaw slice (:func:`streamcal.sim.yaw_slice.yaw_slice`) of the true sensor with channels
    at 10 Hz; ``motor_uT`` µT × ``motor_channel`` (``throttle`` or ``rcou_c1``..``rcou_c5``,
    scaled to 0..1 over the flight) along :data:`MOTOR_DIRECTION` added to the readings."""
    sim = yaw_slice(duration_s, seed, K=A_TRUE, b=B_TRUE, tilt_deg=tilt_deg, field_uT=FIELD_UT,
                    mag_rate_hz=50.0, imu_rate_hz=100.0)
    track = sim.track
    t_mag, mag = track.t_mag, track.mag.copy()
    if motor_channel == "throttle":
        signal = _throttle(t_mag)
    else:
        signal = _pwm(t_mag)[:, int(motor_channel.removeprefix("rcou_c")) - 1]
    span = signal.max() - signal.min()
    mag += motor_uT * ((signal - signal.min()) / span)[:, None] * MOTOR_DIRECTION
    imu = track.accel_rows
    t_ch = np.arange(0.0, duration_s, 0.1) + 0.013
    throttle = _throttle(t_ch)
    return FlightSlice(t_mag, mag, track.t[imu], track.accel, track.gyro,
                       track.columns["temp"][imu], _throttle(t_mag), t_ch, throttle,
                       np.round(_pwm(t_ch)), _volts(t_ch, throttle), _amps(t_ch, throttle),
                       motor_uT=motor_uT)


# ---------------------------------------------------------------- ArduPilot DataFlash (.bin)

HEAD = b"\xa3\x95"
FMT_TYPE = 0x80
#: struct codes of the DataFlash format characters used here (pymavlink's FORMAT_TO_STRUCT).
_STRUCT = {"B": "B", "b": "b", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "Q": "Q",
           "n": "4s", "N": "16s", "Z": "64s"}

#: name → (type id, format, columns): an ArduPilot 4.x layout (MAG with instance and MOfs).
LAYOUT = {
    "FMT": (FMT_TYPE, "BBnNZ", "Type,Length,Name,Format,Columns"),
    "PARM": (0x81, "QNf", "TimeUS,Name,Value"),
    "MSG": (0x82, "QZ", "TimeUS,Message"),
    "MAG": (0x83, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,"
                                   "Health,S"),
    "IMU": (0x84, "QBffffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,Temp,EG"),
    "RCOU": (0x85, "QHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8"),
    "BAT": (0x86, "QBff", "TimeUS,I,Volt,Curr"),
    "CURR": (0x87, "Qhh", "TimeUS,Throttle,Volt"),
    "VER": (0x88, "QBHBBBBIZH", "TimeUS,BT,BST,Maj,Min,Pat,FWT,GH,FWS,APJ"),
}


def _struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(_STRUCT[c] for c in fmt))


def df_message(name: str, *values) -> bytes:
    """One DataFlash message of :data:`LAYOUT` ``name`` (strings as bytes)."""
    type_id, fmt, _ = LAYOUT[name]
    return HEAD + bytes([type_id]) + _struct(fmt).pack(*values)


def df_format(name: str) -> bytes:
    """The FMT message that declares ``name``."""
    type_id, fmt, columns = LAYOUT[name]
    return df_message("FMT", type_id, 3 + _struct(fmt).size, name.encode(), fmt.encode(),
                      columns.encode())


def ardupilot_params(*, motor_comp: np.ndarray | None = None) -> dict:
    """COMPASS_* that calibrate the true sensor exactly: ``S (10 m + o) = 10·FIELD_UT·h``."""
    S = FIELD_UT * np.linalg.inv(A_TRUE)
    o = -10.0 * B_TRUE
    params = {f"COMPASS_OFS_{a}": o[k] for k, a in enumerate("XYZ")}
    params.update({f"COMPASS_DIA_{a}": S[k, k] for k, a in enumerate("XYZ")})
    params.update({"COMPASS_ODI_X": S[0, 1], "COMPASS_ODI_Y": S[0, 2], "COMPASS_ODI_Z": S[1, 2]})
    params["COMPASS_MOTCT"] = 0.0 if motor_comp is None else 1.0
    mot = np.zeros(3) if motor_comp is None else motor_comp
    params.update({f"COMPASS_MOT_{a}": mot[k] for k, a in enumerate("XYZ")})
    params["COMPASS_USE"] = 1.0
    return params


def dataflash_bytes(flight: FlightSlice, *, params: dict | None = None,
                    motor_comp: np.ndarray | None = None, messages=("IMU", "RCOU", "BAT", "CURR"),
                    with_mag: bool = True, c7_not_pwm: bool = False, firmware: str = FIRMWARE,
                    motor_before_matrix: bool = False, version: str | None = None) -> bytes:
    """The log ArduPilot writes for ``flight``: logged MAG = S (10 m + o) + MOfs (mG, int16), or
    with ``motor_before_matrix`` (Copter 3.4–3.5, Plane ≤ 3.8, Rover ≤ 3.2) S (10 m + o + MOfs);
    ``MOfs = COMPASS_MOT · throttle`` when ``motor_comp`` (mG at full throttle) is given; the
    version text ``firmware`` in a MSG message (and ``version`` as the firmware string of a VER
    message, as 4.1 and later log it); RCOU C7 unused (0) or, with ``c7_not_pwm``, a counter far
    outside any PWM range."""
    params = ardupilot_params(motor_comp=motor_comp) if params is None else params
    S = np.array([[params["COMPASS_DIA_X"], params["COMPASS_ODI_X"], params["COMPASS_ODI_Y"]],
                  [params["COMPASS_ODI_X"], params["COMPASS_DIA_Y"], params["COMPASS_ODI_Z"]],
                  [params["COMPASS_ODI_Y"], params["COMPASS_ODI_Z"], params["COMPASS_DIA_Z"]]])
    o = np.array([params[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    mot = np.array([params.get(f"COMPASS_MOT_{a}", 0.0) for a in "XYZ"])
    mofs = np.round(flight.throttle_at_mag[:, None] * mot)
    if motor_before_matrix:
        logged = np.round((10.0 * flight.mag_uT + o + mofs) @ S.T)
    else:
        logged = np.round((10.0 * flight.mag_uT + o) @ S.T + mofs)
    out = [df_format(n) for n in ("FMT", "PARM", "MSG", *(("MAG",) if with_mag else ()),
                                  *messages)]
    if version is not None:
        out.insert(0, df_format("VER"))
        out.append(df_message("VER", 0, 9, 0, 4, 5, 1, 255, 0xB11C6AF3, version.encode(), 9))
    out.append(df_message("MSG", 0, firmware.encode()))
    out += [df_message("PARM", 0, k.encode(), float(v)) for k, v in params.items()]
    rows = []   # (time µs, order, bytes): written in time order, as the firmware does
    if with_mag:
        for t, m, mo in zip(flight.t_mag, logged, mofs):
            rows.append((t, 0, df_message("MAG", int(round(t * 1e6)) + 1000, 0, *map(int, m),
                                          *map(int, o), *map(int, mo), 1, 0)))
    if "IMU" in messages:
        for t, g, a, c in zip(flight.t_imu, flight.gyro, flight.accel, flight.temp):
            rows.append((t, 1, df_message("IMU", int(round(t * 1e6)) + 1000, 0, *g, *a, c, 0.0)))
    for k, t in enumerate(flight.t_ch):
        us = int(round(t * 1e6)) + 1000
        if "RCOU" in messages:
            c7 = 50_000 + 10 * k if c7_not_pwm else 0
            rows.append((t, 2, df_message("RCOU", us, *map(int, flight.pwm[k]), c7, 0)))
        if "BAT" in messages:
            rows.append((t, 3, df_message("BAT", us, 0, flight.volts[k], flight.amps[k])))
        if "CURR" in messages:
            rows.append((t, 4, df_message("CURR", us, int(round(1000 * flight.throttle[k])),
                                          int(round(100 * flight.volts[k])))))
    rows.sort(key=lambda r: (r[0], r[1]))
    return b"".join(out) + b"".join(r[2] for r in rows)


def write_dataflash(path: Path, flight: FlightSlice, **kw) -> Path:
    Path(path).write_bytes(dataflash_bytes(flight, **kw))
    return Path(path)


# ---------------------------------------------------------------- PX4 ULog (.ulg)

ULOG_MAGIC = b"ULog\x01\x12\x35"
_CTYPE = {"uint64_t": "Q", "uint32_t": "I", "int32_t": "i", "uint8_t": "B", "float": "f"}
DEVICE_ID = 396809   # any non-zero id; CAL_MAG0_ID names it
#: topic → fields (C type, name, count), as PX4 declares them in its F messages.
TOPICS = {
    "sensor_mag": [("uint64_t", "timestamp", 1), ("uint32_t", "device_id", 1), ("float", "x", 1),
                   ("float", "y", 1), ("float", "z", 1), ("float", "temperature", 1)],
    "vehicle_magnetometer": [("uint64_t", "timestamp", 1), ("uint32_t", "device_id", 1),
                             ("float", "magnetometer_ga", 3)],
    "sensor_combined": [("uint64_t", "timestamp", 1), ("float", "gyro_rad", 3),
                        ("float", "accelerometer_m_s2", 3)],
    "actuator_outputs": [("uint64_t", "timestamp", 1), ("float", "output", 8)],
    "actuator_controls_0": [("uint64_t", "timestamp", 1), ("float", "control", 8)],
    "battery_status": [("uint64_t", "timestamp", 1), ("float", "voltage_v", 1),
                       ("float", "current_a", 1)],
    "vehicle_attitude": [("uint64_t", "timestamp", 1), ("float", "q", 4)],
    "vehicle_gps_position": [("uint64_t", "timestamp", 1), ("uint64_t", "time_utc_usec", 1),
                             ("int32_t", "lat", 1), ("int32_t", "lon", 1), ("int32_t", "alt", 1),
                             ("uint8_t", "fix_type", 1)],
}


def _umsg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


#: sensor_combined of older PX4 logs: it also carries PX4's calibrated field, the latest sample
#: on each IMU row, stamped relative to the row.
COMBINED_WITH_MAG = TOPICS["sensor_combined"] + [("float", "magnetometer_ga", 3),
                                                 ("int32_t", "magnetometer_timestamp_relative", 1)]


def _topic_struct(fields) -> struct.Struct:
    return struct.Struct("<" + "".join(f"{n}{_CTYPE[c]}" for c, _, n in fields))


def px4_params(*, comp_type: int = 0, rot: int = -1, board_rot: int = 0) -> dict:
    """CAL_MAG0_* (gauss) that calibrate the true sensor: ``S (r − o) = FIELD_UT/100 · h``."""
    S = FIELD_UT * np.linalg.inv(A_TRUE)
    o = B_TRUE / 100.0
    params = {f"CAL_MAG0_{a}OFF": o[k] for k, a in enumerate("XYZ")}
    params.update({f"CAL_MAG0_{a}SCALE": S[k, k] for k, a in enumerate("XYZ")})
    params.update({"CAL_MAG0_XODIAG": S[0, 1], "CAL_MAG0_YODIAG": S[0, 2],
                   "CAL_MAG0_ZODIAG": S[1, 2]})
    params.update({f"CAL_MAG0_{a}COMP": 0.0 for a in "XYZ"})
    ints = {"CAL_MAG0_ID": DEVICE_ID, "CAL_MAG0_ROT": rot, "CAL_MAG_PRIME": DEVICE_ID,
            "SENS_BOARD_ROT": board_rot, "CAL_MAG_COMP_TYP": comp_type}
    return {**params, **ints}


def ulog_head(names, layout: dict, params: dict) -> list[bytes]:
    """The head of a ULog: magic, flag bits, a format per topic of ``names`` (fields from
    ``layout``), the system's name and ``params`` as P messages."""
    out = [ULOG_MAGIC + bytes([1]) + struct.pack("<Q", 0), _umsg(b"B", bytes(40))]
    for name in names:
        fields = "".join(f"{c}{'' if n == 1 else f'[{n}]'} {f};" for c, f, n in layout[name])
        out.append(_umsg(b"F", f"{name}:{fields}".encode()))
    for key, value in (("sys_name", "PX4"), ("ver_hw", "SELFMADE_V1")):
        k = f"char[{len(value)}] {key}".encode()
        out.append(_umsg(b"I", bytes([len(k)]) + k + value.encode()))
    for key, value in params.items():
        kind, code = ("int32_t", "<i") if isinstance(value, int) else ("float", "<f")
        k = f"{kind} {key}".encode()
        out.append(_umsg(b"P", bytes([len(k)]) + k + struct.pack(code, value)))
    return out


def px4_matrix_offsets(params: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(S (3,3), o (3,))`` of CAL_MAG0_*: the symmetric matrix and the offsets, gauss."""
    S = np.array([[params["CAL_MAG0_XSCALE"], params["CAL_MAG0_XODIAG"],
                   params["CAL_MAG0_YODIAG"]],
                  [params["CAL_MAG0_XODIAG"], params["CAL_MAG0_YSCALE"],
                   params["CAL_MAG0_ZODIAG"]],
                  [params["CAL_MAG0_YODIAG"], params["CAL_MAG0_ZODIAG"],
                   params["CAL_MAG0_ZSCALE"]]])
    return S, np.array([params[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])


def ulog_bytes(flight: FlightSlice, *, calibrated: bool = False, combined: bool = False,
               params: dict | None = None,
               topics=("sensor_combined", "actuator_outputs", "actuator_controls_0",
                       "battery_status"), with_mag: bool = True) -> bytes:
    """The ULog PX4 writes for ``flight``: ``sensor_mag`` (the driver's reading, G) or, when
    ``calibrated``, ``vehicle_magnetometer`` = S (r − o) with the CAL_MAG0_* of ``params``; with
    ``combined`` that corrected field rides in ``sensor_combined`` instead (older logs)."""
    params = px4_params() if params is None else params
    layout = dict(TOPICS, sensor_combined=COMBINED_WITH_MAG) if combined else TOPICS
    mag_topic = "vehicle_magnetometer" if calibrated else "sensor_mag"
    names = ([mag_topic] if with_mag and not combined else []) + list(topics)
    out = ulog_head(names, layout, params)
    for msg_id, name in enumerate(names):
        out.append(_umsg(b"A", struct.pack("<BH", 0, msg_id) + name.encode()))
    ids = {name: i for i, name in enumerate(names)}
    rows = []

    def data(t: float, name: str, *values) -> None:
        us = int(round(t * 1e6)) + 1_000_000
        rows.append((us, ids[name], _umsg(b"D", struct.pack("<H", ids[name])
                                          + _topic_struct(layout[name]).pack(us, *values))))

    r_g = flight.mag_uT / 100.0
    if with_mag and (calibrated or combined):
        S, o = px4_matrix_offsets(params)
        corrected = (r_g - o) @ S.T
        if combined:
            latest = np.searchsorted(flight.t_mag, flight.t_imu, side="right") - 1
            for t, g, a, k in zip(flight.t_imu, flight.gyro, flight.accel, latest):
                if k >= 0:
                    relative = int(round(flight.t_mag[k] * 1e6)) - int(round(t * 1e6))
                    data(t, "sensor_combined", *g, *a, *corrected[k], relative)
        else:
            for t, c in zip(flight.t_mag, corrected):
                data(t, "vehicle_magnetometer", DEVICE_ID, *c)
    elif with_mag:
        for t, r in zip(flight.t_mag, r_g):
            data(t, "sensor_mag", DEVICE_ID, *r, 31.5)
    if "sensor_combined" in topics and not combined:
        for t, g, a in zip(flight.t_imu, flight.gyro, flight.accel):
            data(t, "sensor_combined", *g, *a)
    for k, t in enumerate(flight.t_ch):
        if "actuator_outputs" in topics:
            data(t, "actuator_outputs", *flight.pwm[k], 0.0, 0.0)
        if "actuator_controls_0" in topics:
            data(t, "actuator_controls_0", 0.0, 0.0, 0.0, flight.throttle[k], 0, 0, 0, 0)
        if "battery_status" in topics:
            data(t, "battery_status", flight.volts[k], flight.amps[k])
    rows.sort(key=lambda r: (r[0], r[1]))
    return b"".join(out) + b"".join(r[2] for r in rows)


def write_ulog(path: Path, flight: FlightSlice, **kw) -> Path:
    Path(path).write_bytes(ulog_bytes(flight, **kw))
    return Path(path)


# ---------------------------------------------------------------- PX4 flight with attitude and GPS


def px4_mounted_params(mount: np.ndarray, rot: int, S_body: np.ndarray, b_body: np.ndarray,
                       *, comp_g_per_ka=None) -> dict:
    """CAL_MAG0_* (gauss) that calibrate a compass mounted ``mount`` (sensor → body) reading
    ``m = mountᵀ (S_body e + b_body)`` µT: PX4's ``R S (r − o) = e / 100`` with ``R = mount``
    (CAL_MAG0_ROT = ``rot``), so ``S = mountᵀ S_body⁻¹ mount`` and ``o = mountᵀ b_body / 100``;
    ``comp_g_per_ka`` (3,) G/kA on battery 0's current (CAL_MAG_COMP_TYP 2) when given."""
    S = mount.T @ np.linalg.inv(S_body) @ mount
    o = mount.T @ np.asarray(b_body, float) / 100.0
    params = {f"CAL_MAG0_{a}OFF": float(o[k]) for k, a in enumerate("XYZ")}
    params.update({f"CAL_MAG0_{a}SCALE": float(S[k, k]) for k, a in enumerate("XYZ")})
    params.update({"CAL_MAG0_XODIAG": float(S[0, 1]), "CAL_MAG0_YODIAG": float(S[0, 2]),
                   "CAL_MAG0_ZODIAG": float(S[1, 2])})
    comp = np.zeros(3) if comp_g_per_ka is None else np.asarray(comp_g_per_ka, float)
    params.update({f"CAL_MAG0_{a}COMP": float(comp[k]) for k, a in enumerate("XYZ")})
    return {**params, "CAL_MAG0_ID": DEVICE_ID, "CAL_MAG0_ROT": int(rot),
            "CAL_MAG_PRIME": DEVICE_ID, "SENS_BOARD_ROT": 0,
            "CAL_MAG_COMP_TYP": 2 if comp_g_per_ka is not None else 0}


def px4_flight_ulog_bytes(track, params: dict) -> bytes:
    """The ULog PX4 writes for a :func:`streamcal.sim.flight.simulated_log` track: its sensor-
    frame readings as ``sensor_mag`` (G), its attitude as ``vehicle_attitude.q``, its GPS
    position and date as ``vehicle_gps_position`` (1 Hz 3-D fixes), its ``battery_current_a``
    as ``battery_status`` and its accelerometer in ``sensor_combined``; ``params`` as P
    messages."""
    import datetime

    names = ["sensor_mag", "vehicle_attitude", "vehicle_gps_position", "sensor_combined"]
    if track.has("battery_current_a"):
        names.append("battery_status")
    out = ulog_head(names, TOPICS, params)
    ids = {name: i for i, name in enumerate(names)}
    out += [_umsg(b"A", struct.pack("<BH", 0, i) + name.encode()) for name, i in ids.items()]
    rows = []

    def data(t: float, name: str, *values) -> None:
        us = int(round(t * 1e6)) + 1_000_000
        rows.append((us, ids[name], _umsg(b"D", struct.pack("<H", ids[name])
                                          + _topic_struct(TOPICS[name]).pack(us, *values))))

    t = track.t_mag
    q = np.column_stack([track.columns[c][track.mag_rows] for c in
                         ("att_qw", "att_qx", "att_qy", "att_qz")])
    accel = track.accel
    for k, tk in enumerate(t):
        data(tk, "sensor_mag", DEVICE_ID, *(track.mag[k] / 100.0), 31.5)
        data(tk + 0.001, "vehicle_attitude", *q[k])
        data(tk + 0.002, "sensor_combined", 0.0, 0.0, 0.0, *accel[k])
        if "battery_status" in ids:
            data(tk + 0.003, "battery_status", 12.0,
                 float(track.columns["battery_current_a"][track.mag_rows][k]))
    meta = track.metadata
    day = datetime.datetime.fromisoformat(meta["gps_date"]).replace(
        tzinfo=datetime.timezone.utc)
    lat, lon = float(meta["gps_lat_deg"]), float(meta["gps_lon_deg"])
    for tk in np.arange(t[0], t[-1], 1.0):
        utc = int((day.timestamp() + 12 * 3600 + tk) * 1e6)
        data(tk + 0.004, "vehicle_gps_position", utc, int(round(lat * 1e7)),
             int(round(lon * 1e7)), int(round(float(meta["gps_alt_m"]) * 1e3)), 3)
    rows.sort(key=lambda r: (r[0], r[1]))
    return b"".join(out) + b"".join(r[2] for r in rows)
