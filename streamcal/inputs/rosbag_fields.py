"""The fields streamcal reads from sensor_msgs messages, for all messages of a topic at once.

:func:`decode` returns ``{"stamp_ns": (n,) int64, "frame_ids": [str], FIELD: (n, k) float64}``
for the message type's fields in :data:`FIELDS`. Messages of one topic from one driver usually
have one length (a fixed frame id): they are then decoded with numpy from their serialized bytes
(ROS 1: packed little-endian; ROS 2: CDR little-endian, aligned after its 4-byte encapsulation
header), and the first, middle and last messages are checked against rosbags' own
deserialization. Anything else (lengths that differ, big-endian CDR, a check that fails) is
deserialized message by message with rosbags.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

#: message type → (alignment of the body in CDR, {field: (dtype, byte offset in the body, k)});
#: ``*_covariance0`` is element 0 of the covariance (−1 declares the field absent, REP 145)
FIELDS = {
    "sensor_msgs/msg/MagneticField": (8, {"magnetic_field": ("<f8", 0, 3)}),
    "sensor_msgs/msg/Imu": (8, {"angular_velocity": ("<f8", 104, 3),
                                "angular_velocity_covariance0": ("<f8", 128, 1),
                                "linear_acceleration": ("<f8", 200, 3),
                                "linear_acceleration_covariance0": ("<f8", 224, 1)}),
    "sensor_msgs/msg/Temperature": (8, {"temperature": ("<f8", 0, 1)}),
    "sensor_msgs/msg/BatteryState": (4, {"current": ("<f4", 8, 1)}),
}
_CDR_LE = b"\x00\x01"


def _from_message(msg, field: str, k: int) -> np.ndarray:
    if field.endswith("_covariance0"):
        return np.array([getattr(msg, field[:-1])[0]], dtype=np.float64)
    value = getattr(msg, field)
    if k == 3:
        return np.array([value.x, value.y, value.z], dtype=np.float64)
    return np.array([value], dtype=np.float64)


def _stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _one_by_one(raws, msgtype: str, deserialize: Callable) -> dict:
    msgs = [deserialize(raw, msgtype) for raw in raws]
    out = {"stamp_ns": np.array([_stamp_ns(m) for m in msgs], dtype=np.int64),
           "frame_ids": sorted({m.header.frame_id for m in msgs})}
    for field, (_, _, k) in FIELDS[msgtype][1].items():
        out[field] = np.array([_from_message(m, field, k) for m in msgs],
                              dtype=np.float64).reshape(-1, k)
    return out


def _vectorized(raws: Sequence[bytes], msgtype: str, ros2: bool) -> dict | None:
    length = len(raws[0])
    if length < 16 or any(len(r) != length for r in raws):
        return None
    if ros2 and raws[0][:2] != _CDR_LE:
        return None
    data = np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), length)
    strlen = data[:, 12:16].copy().view("<u4")[:, 0]
    if np.any(strlen != strlen[0]):
        return None
    start = 16 + int(strlen[0])
    align, fields = FIELDS[msgtype]
    if ros2:
        start = 4 + -(-(start - 4) // align) * align
    names = data[:, 16:16 + int(strlen[0]) - (1 if ros2 else 0)]
    stamps = data[:, 4:12].copy().view("<u4")
    sec = stamps[:, 0].view("<i4") if ros2 else stamps[:, 0]
    out = {"stamp_ns": sec.astype(np.int64) * 1_000_000_000 + stamps[:, 1].astype(np.int64),
           "frame_ids": sorted({bytes(row).decode("utf-8", "replace")
                                for row in np.unique(names, axis=0)})}
    for field, (dtype, offset, k) in fields.items():
        size = np.dtype(dtype).itemsize * k
        if start + offset + size > length:
            return None
        chunk = data[:, start + offset:start + offset + size].copy()
        out[field] = chunk.view(dtype).astype(np.float64).reshape(-1, k)
    return out


def _agrees(out: dict, raws, msgtype: str, deserialize: Callable) -> bool:
    for i in sorted({0, len(raws) // 2, len(raws) - 1}):
        msg = deserialize(raws[i], msgtype)
        if out["stamp_ns"][i] != _stamp_ns(msg) or msg.header.frame_id not in out["frame_ids"]:
            return False
        for field, (_, _, k) in FIELDS[msgtype][1].items():
            if not np.array_equal(out[field][i], _from_message(msg, field, k), equal_nan=True):
                return False
    return True


def decode(raws: Sequence[bytes], msgtype: str, deserialize: Callable, *, ros2: bool) -> dict:
    """The fields of :data:`FIELDS` of ``raws`` (serialized ``msgtype`` messages, n ≥ 1)."""
    out = _vectorized(raws, msgtype, ros2)
    if out is not None and _agrees(out, raws, msgtype, deserialize):
        return out
    return _one_by_one(raws, msgtype, deserialize)
