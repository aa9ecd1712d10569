"""Write ``vectors.json``: message fields → exact wire bytes from the Python encoder.

    python arduino/test_vectors/make_vectors.py      # from the repository root

``tests/test_arduino_build.py`` checks that the file matches the current encoder and that the
C++ codec (``sc_protocol.h`` via ``sc_vectors.cpp``) produces and decodes the same bytes.
Floats are also given as their binary32 bit patterns (``args``) so no precision is lost in text.
"""
from __future__ import annotations

import json
import math
import struct
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))

from firmware_bridge import frames as fr  # noqa: E402
from firmware_bridge.selfcal_frames import CalOrigin, SelfCal, SelfCalEvent, SelfCalReason  # noqa: E402
from firmware_bridge.fake_board import apply_calibration_f32, mag_scale_from_asa, sphere_sums_add  # noqa: E402


def _bits(value: float) -> int:
    return struct.unpack("<I", struct.pack("<f", value))[0]


def args_of(msg: fr.Message) -> list[int]:
    """Body values in wire order, floats as binary32 bit patterns."""
    codes = [code for _, code, count in msg.LAYOUT for _ in range(count)]
    return [_bits(v) if c == "f" else int(v) for v, c in zip(msg.values(), codes)]


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def messages() -> list[tuple[str, int, fr.Message]]:
    cal = fr.SetCalibration.from_kb([[48.5, -1.25, 0.75], [0, 51.0, 2.5], [0, 0, 49.75]],
                                    [12.0, -7.5, 30.25], cal_id=0xBEEF)
    return [
        ("hello", 0, fr.Hello(fw_major=1, fw_minor=0, whoami=0x71, ak_wia=0x48, flags=7, period_us=10000,
                              accel_scale=_f32(9.80665 / 8192), gyro_scale=_f32(math.pi / 180 / 16.4),
                              temp_scale=_f32(1 / 333.87), temp_offset=21.0,
                              mag_scale=mag_scale_from_asa((49, 48, 37)))),   # body x y z: (ASA+128) 176 177 165
        ("sample", 1, fr.Sample(t_us=123456789, mag=(-32768, 0, 32767), accel=(1, -1, 8192),
                                gyro=(0, 256, -256), temp=-1234, status=0x3D)),
        ("sample_zeros", 0xFFFF, fr.Sample()),
        ("cal_sample", 0x1234, fr.CalSample(t_us=0xFFFFFFFF, x=(-0.0, 1.0, _f32(-0.7071067811865476)), status=0x81)),
        ("sphere_sums", 42, fr.SphereSums(n=3, rejected=1, center=(100, -200, 300), s1=(1, -2, 3),
                                          s2=(10, -20, 30, 40, -50, 60), s3=tuple(range(-4, 5)),
                                          s4=(1 << 40, 5, 6, 7, (1 << 62) + 1, 9))),
        ("cal_report", 7, fr.CalReport(valid=1, cal_id=cal.cal_id, k=cal.k, b=cal.b, crc=cal.crc)),
        ("ack", 8, fr.Ack(acked_type=fr.MsgType.SET_CAL, acked_seq=65535)),
        ("nak", 9, fr.Nak(acked_type=fr.MsgType.SET_CAL, acked_seq=3, reason=fr.NakReason.BAD_CAL_CRC)),
        ("get_info", 0, fr.GetInfo()),
        ("start", 10, fr.Start(outputs=0x0F, period_us=5000, sums_every=100)),
        ("stop", 11, fr.Stop()),
        ("set_cal", 12, cal),
        ("query_cal", 13, fr.QueryCal()),
        ("clear_cal", 14, fr.ClearCal()),
        # the board's own calibration: a fit (candidate K = R I) and a decision with NaN loss_old
        ("self_cal_fitted", 15, _self_cal(SelfCalEvent.FITTED, SelfCalReason.NONE, CalOrigin.HOST, 0xBEEF,
                                          loss_old=_f32(0.0123))),
        ("self_cal_accepted", 16, _self_cal(SelfCalEvent.ACCEPTED, SelfCalReason.NO_CAL_IN_FORCE,
                                            CalOrigin.BOARD, 0xB001, loss_old=math.nan)),
    ]


def _self_cal(event, reason, origin, in_force_id, loss_old) -> SelfCal:
    cand = fr.SetCalibration.from_kb(np.diag([_f32(48.75)] * 3), [_f32(11.5), _f32(-7.25), _f32(30.0)],
                                     cal_id=0xB001)
    return SelfCal(event=int(event), reason=int(reason), origin=int(origin), in_force_id=in_force_id, cells=57,
                   n_fit=5123, n_check=2600, fit_cost=_f32(0.00042), loss_new=_f32(0.0017), loss_old=loss_old,
                   fit_cycles=1234567, sample_cycles=2345, cal_id=cand.cal_id, k=cand.k, b=cand.b, crc=cand.crc)


def build() -> dict:
    frames = [{"name": name, "type": int(msg.TYPE), "seq": seq, "args": args_of(msg),
               "fields": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(msg).items()},
               "hex": fr.encode(msg, seq).hex()} for name, seq, msg in messages()]
    good = bytes.fromhex(frames[1]["hex"])
    flipped = bytearray(good)
    flipped[5] ^= 0x01
    bad = [
        {"name": "bad_crc", "hex": bytes(flipped).hex()},
        {"name": "truncated", "hex": (good[:10] + b"\x00").hex()},
        {"name": "cobs_overrun", "hex": "0f0102" + "00"},
        {"name": "too_short", "hex": (fr.cobs.encode(b"\x01\x02\x03") + b"\x00").hex()},
    ]
    mag = [[100, -200, 300], [150, -180, 320], [90, -260, 280], [3000, 0, 0], [-32768, 32767, 5], [101, -199, 299]]
    sums = sphere_sums_add(fr.SphereSums(), mag)
    cal = dict((name, msg) for name, _, msg in messages())["set_cal"]
    m = [[40.5, -12.25, 7.0], [-3.0, 55.5, -41.0]]
    x = apply_calibration_f32(cal, m)
    return {
        "protocol_version": fr.PROTOCOL_VERSION,
        "crc_check": {"input": "123456789", "crc16": fr.crc16(b"123456789")},
        "frames": frames,
        "bad": bad,
        "sums": {"mag": mag, "args": args_of(sums)},
        "apply": [{"k": [_bits(v) for v in cal.k], "b": [_bits(v) for v in cal.b],
                   "m": [_bits(v) for v in row], "x": [_bits(float(v)) for v in xr]} for row, xr in zip(m, x)],
        "cal_check": {"k": [_bits(v) for v in cal.k], "b": [_bits(v) for v in cal.b], "cal_id": cal.cal_id,
                      "crc": cal.crc},
    }


def render() -> str:
    return json.dumps(build(), indent=1) + "\n"


if __name__ == "__main__":
    (HERE / "vectors.json").write_text(render())
    print(f"wrote {HERE / 'vectors.json'}")
