"""Self-made PX4 ULogs of the layouts streamcal has no real log of, for tests.

Bytes per the ULog file format (16-byte header, then ``F`` formats, ``I`` info, ``P``
parameters, ``A`` subscriptions with their multi-instance, ``D`` data). Layouts:

* ``"1.9"``: ``sensor_mag`` as PX4's drivers published it before the calibration moved into the
  sensors module (``PX4Magnetometer``: fields ``x_raw``, ``scaling``, ``is_external``; ``x, y, z``
  already ``(r − CAL_MAGn_xOFF) · CAL_MAGn_xSCALE``, no off-diagonal terms), ``ver_sw_release``
  1.9.2;
* ``"1.14"``: ``sensor_mag`` the uncalibrated reading (``timestamp_sample``, ``error_count``),
  CAL_MAGn_PRIO, ODIAG, ``ver_sw_release`` 1.14.0;
* ``"1.14-vm"``: only ``vehicle_magnetometer``, one instance per compass, PX4's corrected field
  ``S (r − o)`` with its ``device_id``.

Compass ``k`` (``sensor_mag`` instance ``k``) reads ``r_k = A_k e + o_k`` gauss, ``e`` the
body-frame earth field (no rotations: CAL_MAGn_ROT −1, SENS_BOARD_ROT 0); CAL_MAGn_* hold the
exact calibration ``S_k = A_k⁻¹`` (diagonal in 1.9), ``o_k``. ``vehicle_attitude`` and
``sensor_combined`` come with it.
"""
from __future__ import annotations

import struct

import numpy as np

from ._vehicle_logs import GRAVITY, LAT, LON, flight_profile

_CODE = {"uint64_t": "Q", "uint32_t": "I", "int32_t": "i", "int16_t": "h", "uint8_t": "B",
         "bool": "?", "float": "f"}
IDS = (197388, 197644, 197900)

LAYOUTS = {
    "1.9": {"sensor_mag": [("uint64_t", "timestamp"), ("uint32_t", "device_id"),
                           ("uint32_t", "error_count"), ("float", "x"), ("float", "y"),
                           ("float", "z"), ("float", "range_ga"), ("float", "scaling"),
                           ("float", "temperature"), ("int16_t", "x_raw"), ("int16_t", "y_raw"),
                           ("int16_t", "z_raw"), ("bool", "is_external")],
            "release": 0x010902FF},
    "1.14": {"sensor_mag": [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                            ("uint32_t", "device_id"), ("float", "x"), ("float", "y"),
                            ("float", "z"), ("float", "temperature"),
                            ("uint32_t", "error_count")],
             "release": 0x010E00FF},
    "1.14-vm": {"vehicle_magnetometer": [("uint64_t", "timestamp"),
                                         ("uint64_t", "timestamp_sample"),
                                         ("uint32_t", "device_id"), ("float[3]", "magnetometer_ga"),
                                         ("uint8_t", "calibration_count")],
                "release": 0x010E00FF},
}
_OTHER = {"sensor_combined": [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"),
                              ("float[3]", "accelerometer_m_s2")],
          "vehicle_attitude": [("uint64_t", "timestamp"), ("float[4]", "q")],
          "vehicle_thrust_setpoint": [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                                      ("float[3]", "xyz")]}


def _m(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _fmt(fields) -> str:
    return "<" + "".join(_CODE[c.split("[")[0]] * (int(c.split("[")[1][:-1]) if "[" in c else 1)
                         for c, _ in fields)


def write_px4_log(path, version: str, A: list, offsets_g: list, *, seconds: float = 60.0,
                  seed: int = 0, prio=None, prime: int = 0) -> dict:
    """Write a ULog of ``version`` (:data:`LAYOUTS`) with one ``sensor_mag`` instance per
    compass (soft iron ``A[k]`` (3,3), offsets ``offsets_g[k]`` (3,) G). Returns the truth
    ``{"e": (n,3) body field G, "raw": [(n,3) r_k G]}``."""
    from streamcal.geomag import ned_field, parse_date, wmm_field

    layout = LAYOUTS[version]
    mag_topic = "vehicle_magnetometer" if version.endswith("-vm") else "sensor_mag"
    topics = {mag_topic: layout[mag_topic], **_OTHER}
    t, att, _, _, throttle = flight_profile(seconds, seed)
    e = att.inv().apply(ned_field(wmm_field(LAT, LON, 0.58, parse_date("2024-03-10")))) / 100.0
    accel = att.inv().apply([0.0, 0.0, -GRAVITY])
    q = att.as_quat()[:, [3, 0, 1, 2]]
    out = [b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0), _m(b"B", bytes(40))]
    for name, fields in topics.items():
        out.append(_m(b"F", f"{name}:{''.join(f'{c} {f};' for c, f in fields)}".encode()))
    for key, value in (("sys_name", b"PX4"), ("ver_hw", b"SELFMADE_V5")):
        k = f"char[{len(value)}] {key}".encode()
        out.append(_m(b"I", bytes([len(k)]) + k + value))
    k = b"uint32_t ver_sw_release"
    out.append(_m(b"I", bytes([len(k)]) + k + struct.pack("<I", layout["release"])))
    params: dict = {"SENS_BOARD_ROT": 0, "CAL_MAG_PRIME": IDS[prime]}
    for c, (Ak, off) in enumerate(zip(A, offsets_g)):
        S = np.linalg.inv(Ak)
        params[f"CAL_MAG{c}_ID"] = IDS[c]
        params[f"CAL_MAG{c}_ROT"] = -1
        for i, a in enumerate("XYZ"):
            params[f"CAL_MAG{c}_{a}OFF"] = float(off[i])
            params[f"CAL_MAG{c}_{a}SCALE"] = float(S[i, i])
        if version != "1.9":
            params[f"CAL_MAG{c}_PRIO"] = int(prio[c]) if prio else 50
            for a, v in zip("XYZ", (S[0, 1], S[0, 2], S[1, 2])):
                params[f"CAL_MAG{c}_{a}ODIAG"] = float(v)
    for key, value in params.items():
        kind, code = ("int32_t", "<i") if isinstance(value, int) else ("float", "<f")
        kk = f"{kind} {key}".encode()
        out.append(_m(b"P", bytes([len(kk)]) + kk + struct.pack(code, value)))
    out.append(_m(b"A", struct.pack("<BH", 0, 0) + b"sensor_combined"))
    out.append(_m(b"A", struct.pack("<BH", 0, 1) + b"vehicle_attitude"))
    out.append(_m(b"A", struct.pack("<BH", 0, 9) + b"vehicle_thrust_setpoint"))
    for c in range(len(A)):
        out.append(_m(b"A", struct.pack("<BH", c, 2 + c) + mag_topic.encode()))
    raws = [e @ np.asarray(Ak).T + np.asarray(off) for Ak, off in zip(A, offsets_g)]
    mag_fmt = _fmt(layout[mag_topic])
    for i, ti in enumerate(t):
        us = 1_000_000 + int(round(ti * 1e6))
        out.append(_m(b"D", struct.pack("<H", 0) + struct.pack(_fmt(_OTHER["sensor_combined"]),
                                                                us, 0, 0, 0, *accel[i])))
        out.append(_m(b"D", struct.pack("<H", 1) + struct.pack(_fmt(_OTHER["vehicle_attitude"]),
                                                                us, *q[i])))
        out.append(_m(b"D", struct.pack("<H", 9) + struct.pack(
            _fmt(_OTHER["vehicle_thrust_setpoint"]), us, us, 0.02, 0.0, -throttle[i])))
        for c, r in enumerate(raws):
            if version == "1.9":    # the driver's output: offsets off, diagonal scale applied
                diag = np.array([params[f"CAL_MAG{c}_{a}SCALE"] for a in "XYZ"])
                x = (r[i] - offsets_g[c]) * diag
                values = (us, IDS[c], 0, *x, 4.0, 0.0015, 35.0,
                          *(int(v) for v in np.round(r[i] / 0.0015)),
                          c > 0)
            elif mag_topic == "vehicle_magnetometer":
                values = (us, us - 300, IDS[c], *(np.linalg.inv(A[c]) @ (r[i] - offsets_g[c])), 0)
            else:
                values = (us, us - 300, IDS[c], *r[i], 35.0, 0)
            out.append(_m(b"D", struct.pack("<H", 2 + c) + struct.pack(mag_fmt, *values)))
    with open(path, "wb") as fh:
        fh.write(b"".join(out))
    return {"e": e, "raw": raws, "throttle": throttle}
