"""Self-made PX4 ULog files with several ``sensor_mag`` instances and their CAL_MAGn_*, for tests.

Bytes per the ULog file format (docs.px4.io "ULog File Format"): a 16-byte header (magic, version,
start timestamp), then messages ``uint16 size, uint8 type, payload``: ``F`` formats, ``P``
parameters, ``A`` subscriptions (multi-instance + message id + name), ``D`` data, ``S`` sync
(a magic to resynchronise on after damaged bytes).

Compass ``k`` (``sensor_mag`` instance ``k``, device id ``ids[k]``) reads ``r = f + o_k`` gauss
(PX4 corrects ``c = S (r − o)`` with S = I, so the corrected field is the true body field ``f``).
"""
from __future__ import annotations

import struct

import numpy as np

from ._dataflash_log import EARTH_NED, G, tumble

GAUSS_PER_MG = 1e-3
SYNC = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"   # the sync message's magic


def _msg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _param(name: str, value) -> bytes:
    key = (f"int32_t {name}" if isinstance(value, int) else f"float {name}").encode()
    packed = struct.pack("<i", value) if isinstance(value, int) else struct.pack("<f", value)
    return _msg(b"P", bytes([len(key)]) + key + packed)


def write_ulog(path, offsets_g, *, ids=(197388, 197644, 197900), prio=None, seconds=60.0,
               seed=0) -> dict:
    """Write a log with one ``sensor_mag`` instance per entry of ``offsets_g`` ((3,) gauss each),
    ``sensor_combined`` accelerometer/gyro at 50 Hz and CAL_MAGn_ID/PRIO/XOFF... parameters.
    Returns ``{"field_g": (n,3) body field at the mag instants}``."""
    t, rot, rates = tumble(seconds, 50.0, seed)
    t_us = (t * 1e6).astype(np.int64) + 1_000_000
    f_g = rot.inv().apply(EARTH_NED) * GAUSS_PER_MG
    accel = rot.inv().apply([0.0, 0.0, -G])
    out = [b"ULog\x01\x12\x35", bytes([1]), struct.pack("<Q", int(t_us[0]))]
    out.append(_msg(b"F", b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;"
                          b"float z;float temperature;"))
    out.append(_msg(b"F", b"sensor_combined:uint64_t timestamp;float[3] gyro_rad;"
                          b"float[3] accelerometer_m_s2;"))
    for k, off in enumerate(offsets_g):
        out.append(_param(f"CAL_MAG{k}_ID", ids[k]))
        out.append(_param(f"CAL_MAG{k}_PRIO", int(prio[k]) if prio else 50))
        out.append(_param(f"CAL_MAG{k}_ROT", -1))
        for a, v in zip("XYZ", off):
            out.append(_param(f"CAL_MAG{k}_{a}OFF", float(v)))
            out.append(_param(f"CAL_MAG{k}_{a}SCALE", 1.0))
    out.append(_param("SENS_BOARD_ROT", 0))
    out.append(_msg(b"A", struct.pack("<BH", 0, 0) + b"sensor_combined"))
    for k in range(len(offsets_g)):
        out.append(_msg(b"A", struct.pack("<BH", k, k + 1) + b"sensor_mag"))
    for i in range(len(t)):
        if i % 50 == 0:     # a sync message each second, as PX4's logger writes them
            out.append(_msg(b"S", SYNC))
        out.append(_msg(b"D", struct.pack("<HQ6f", 0, int(t_us[i]), *rates[i], *accel[i])))
        if i % 5:
            continue
        for k, off in enumerate(offsets_g):
            r = f_g[i] + np.asarray(off, float)
            out.append(_msg(b"D", struct.pack("<HQI4f", k + 1, int(t_us[i]), ids[k], *r, 35.0)))
    with open(path, "wb") as fh:
        fh.write(b"".join(out))
    return {"field_g": f_g[::5]}
