"""The messages of the serial protocol shared with the Arduino sketch (``PROTOCOL.md``): their
types, fields and fixed-size little-endian bodies. The codec is :mod:`firmware_bridge.frames`.
"""
from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection); ``crc16(b"123456789") == 0x29B1``.

    The stdlib's ``binascii.crc_hqx`` with init 0xFFFF is this CRC, in C: about 500× faster than
    the ``crc`` package's table mode on 30-byte frames. Tests check it against
    ``crc.Crc16.IBM_3740`` (the catalogue name of CRC-16/CCITT-FALSE).
    """
    return binascii.crc_hqx(data, 0xFFFF)


def cal_block_crc(cal_id: int, k, b) -> int:
    """CRC-16/CCITT-FALSE of the packed ``cal_id:u16 k:6×f32 b:3×f32`` (38 bytes)."""
    return crc16(struct.pack("<H6f3f", cal_id, *k, *b))


def unpack_k(k) -> np.ndarray:
    """(6,) upper triangle k11 k12 k13 k22 k23 k33 → (3,3) float64."""
    K = np.zeros((3, 3))
    K[np.triu_indices(3)] = np.asarray(k, dtype=float)
    return K



class MsgType(enum.IntEnum):
    """Message types; 0x0_ board → host, 0x1_ host → board."""

    HELLO = 0x01
    SAMPLE = 0x02
    CAL_SAMPLE = 0x03
    SPHERE_SUMS = 0x04
    CAL_REPORT = 0x05
    ACK = 0x06
    NAK = 0x07
    SELF_CAL = 0x08       # firmware_bridge/selfcal_frames.py
    GET_INFO = 0x10
    START = 0x11
    STOP = 0x12
    SET_CAL = 0x13
    QUERY_CAL = 0x14
    CLEAR_CAL = 0x15


class Status(enum.IntFlag):
    """``status`` byte of SAMPLE and CAL_SAMPLE."""

    MAG_VALID = 0x01      # a new magnetometer sample is in this frame
    MAG_OVERFLOW = 0x02   # AK8963 ST2.HOFL: sample discarded (mag fields are 0)
    MAG_OVERRUN = 0x04    # AK8963 ST1.DOR: at least one mag sample was skipped
    ACCEL_VALID = 0x08
    GYRO_VALID = 0x10
    TEMP_VALID = 0x20
    I2C_ERROR = 0x40      # a bus transaction failed while reading this sample
    CAL_ACTIVE = 0x80     # the board holds a valid calibration


class HelloFlags(enum.IntFlag):
    CAL_LOADED = 0x01     # a valid calibration was found in EEPROM (or set since boot)
    MAG_PRESENT = 0x02    # AK8963 answered WIA = 0x48
    STREAMING = 0x04
    SELF_CAL = 0x08       # the firmware calibrates itself (SELF_CAL frames)


class Output(enum.IntFlag):
    """``outputs`` byte of START."""

    SAMPLES = 0x01
    CALIBRATED = 0x02
    SPHERE_SUMS = 0x04
    RESET_SUMS = 0x08     # zero the sphere sums before streaming


class NakReason(enum.IntEnum):
    BAD_CAL_CRC = 1       # the calibration block's own CRC does not match
    BAD_CAL_VALUES = 2    # non-finite number or non-positive diagonal of K
    UNKNOWN_TYPE = 3
    BAD_LENGTH = 4
    BAD_VERSION = 5
    EEPROM_FAILED = 6     # read-back after writing did not match


# -- messages -------------------------------------------------------------------------------
# Each message declares its body as (field, struct code, count); arrays are tuples.

class Message:
    TYPE: ClassVar[MsgType]
    LAYOUT: ClassVar[tuple[tuple[str, str, int], ...]] = ()
    _struct: ClassVar[struct.Struct]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls._struct = struct.Struct("<" + "".join(f"{n}{c}" for _, c, n in cls.LAYOUT))

    def values(self) -> list:
        """The body's scalar values in wire order (arrays flattened)."""
        out = []
        for name, _, count in self.LAYOUT:
            value = getattr(self, name)
            out.extend(value if count > 1 else (value,))
        return out

    def pack_body(self) -> bytes:
        return self._struct.pack(*self.values())

    @classmethod
    def from_values(cls, values) -> "Message":
        kwargs, i = {}, 0
        for name, _, count in cls.LAYOUT:
            kwargs[name] = tuple(values[i:i + count]) if count > 1 else values[i]
            i += count
        return cls(**kwargs)

    @classmethod
    def unpack_body(cls, body: bytes) -> "Message":
        return cls.from_values(cls._struct.unpack(body))

    @classmethod
    def body_size(cls) -> int:
        return cls._struct.size


@dataclass(frozen=True)
class Hello(Message):
    """Board identity and the scales that turn counts into SI units.

    ``mag_scale`` is µT per count per body axis (AK8963 4912/32760 µT/LSB × fuse-ROM ASA factor, after
    the axis remap); ``accel_scale`` m/s² per count; ``gyro_scale`` rad/s per count; temperature
    °C = count × ``temp_scale`` + ``temp_offset``; ``period_us`` the sample period.
    """

    TYPE: ClassVar = MsgType.HELLO
    LAYOUT: ClassVar = (("fw_major", "B", 1), ("fw_minor", "B", 1), ("whoami", "B", 1),
                        ("ak_wia", "B", 1), ("flags", "B", 1), ("period_us", "I", 1),
                        ("accel_scale", "f", 1), ("gyro_scale", "f", 1), ("temp_scale", "f", 1),
                        ("temp_offset", "f", 1), ("mag_scale", "f", 3))
    fw_major: int = 1
    fw_minor: int = 0
    whoami: int = 0x71
    ak_wia: int = 0x48
    flags: int = 0
    period_us: int = 10000
    accel_scale: float = 0.0
    gyro_scale: float = 0.0
    temp_scale: float = 0.0
    temp_offset: float = 0.0
    mag_scale: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Sample(Message):
    """One instant in raw counts, body (accelerometer) axes; see :class:`Status` for validity."""

    TYPE: ClassVar = MsgType.SAMPLE
    LAYOUT: ClassVar = (("t_us", "I", 1), ("mag", "h", 3), ("accel", "h", 3), ("gyro", "h", 3),
                        ("temp", "h", 1), ("status", "B", 1))
    t_us: int = 0
    mag: tuple = (0, 0, 0)
    accel: tuple = (0, 0, 0)
    gyro: tuple = (0, 0, 0)
    temp: int = 0
    status: int = 0


@dataclass(frozen=True)
class CalSample(Message):
    """The board's calibrated direction ``x = K⁻¹(m − b)`` (float32, unitless) at ``t_us``."""

    TYPE: ClassVar = MsgType.CAL_SAMPLE
    LAYOUT: ClassVar = (("t_us", "I", 1), ("x", "f", 3), ("status", "B", 1))
    t_us: int = 0
    x: tuple = (0.0, 0.0, 0.0)
    status: int = 0


SUM_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True)
class SphereSums(Message):
    """The 25 sufficient statistics of the one-pass sphere fit, over mag counts ``d = m − center``.

    ``s1[j] = Σ d_j``; ``s2[p] = Σ d_j d_k`` and ``s4[p] = Σ d_j² d_k²`` for the pairs
    :data:`SUM_PAIRS`; ``s3[3j+k] = Σ d_j² d_k``; ``n`` samples summed (the 25th statistic).
    Samples with any ``|d_j| > 2047`` are not summed but counted in ``rejected``; summing stops at
    ``n = 2**19`` so the int64 sums cannot overflow.
    """

    TYPE: ClassVar = MsgType.SPHERE_SUMS
    LAYOUT: ClassVar = (("n", "I", 1), ("rejected", "I", 1), ("center", "h", 3), ("s1", "q", 3),
                        ("s2", "q", 6), ("s3", "q", 9), ("s4", "q", 6))
    n: int = 0
    rejected: int = 0
    center: tuple = (0, 0, 0)
    s1: tuple = (0,) * 3
    s2: tuple = (0,) * 6
    s3: tuple = (0,) * 9
    s4: tuple = (0,) * 6


@dataclass(frozen=True)
class SetCalibration(Message):
    """Host → board: ``K`` (upper triangle k11 k12 k13 k22 k23 k33) and ``b``, µT, float32, with the
    block's own CRC-16 over (cal_id, k, b) so the board can store and re-check it in EEPROM."""

    TYPE: ClassVar = MsgType.SET_CAL
    LAYOUT: ClassVar = (("cal_id", "H", 1), ("k", "f", 6), ("b", "f", 3), ("crc", "H", 1))
    cal_id: int = 0
    k: tuple = (1.0, 0.0, 0.0, 1.0, 0.0, 1.0)
    b: tuple = (0.0, 0.0, 0.0)
    crc: int = 0

    @classmethod
    def from_kb(cls, K, b, cal_id: int = 0) -> "SetCalibration":
        """Build the block from a (3,3) upper-triangular ``K`` and (3,) ``b`` (µT), CRC filled in."""
        K = np.asarray(K, dtype=np.float32)
        k = tuple(float(v) for v in K[np.triu_indices(3)])
        b = tuple(float(v) for v in np.asarray(b, dtype=np.float32).reshape(3))
        return cls(cal_id=cal_id, k=k, b=b, crc=cal_block_crc(cal_id, k, b))

    def crc_ok(self) -> bool:
        return self.crc == cal_block_crc(self.cal_id, self.k, self.b)

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K (3,3), b (3,))`` as float64."""
        return unpack_k(self.k), np.array(self.b, dtype=float)


@dataclass(frozen=True)
class CalReport(Message):
    """Board → host: the calibration in use (``valid`` 0 = none); same block as SET_CAL."""

    TYPE: ClassVar = MsgType.CAL_REPORT
    LAYOUT: ClassVar = (("valid", "B", 1),) + SetCalibration.LAYOUT
    valid: int = 0
    cal_id: int = 0
    k: tuple = (0.0,) * 6
    b: tuple = (0.0,) * 3
    crc: int = 0


@dataclass(frozen=True)
class Ack(Message):
    TYPE: ClassVar = MsgType.ACK
    LAYOUT: ClassVar = (("acked_type", "B", 1), ("acked_seq", "H", 1))
    acked_type: int = 0
    acked_seq: int = 0


@dataclass(frozen=True)
class Nak(Message):
    TYPE: ClassVar = MsgType.NAK
    LAYOUT: ClassVar = (("acked_type", "B", 1), ("acked_seq", "H", 1), ("reason", "B", 1))
    acked_type: int = 0
    acked_seq: int = 0
    reason: int = 0


@dataclass(frozen=True)
class GetInfo(Message):
    TYPE: ClassVar = MsgType.GET_INFO


@dataclass(frozen=True)
class Start(Message):
    """``outputs``: :class:`Output` bits; ``period_us`` 0 keeps the current period;
    ``sums_every``: send SPHERE_SUMS every that many mag samples (0 = never)."""

    TYPE: ClassVar = MsgType.START
    LAYOUT: ClassVar = (("outputs", "B", 1), ("period_us", "I", 1), ("sums_every", "H", 1))
    outputs: int = int(Output.SAMPLES | Output.CALIBRATED | Output.SPHERE_SUMS)
    period_us: int = 0
    sums_every: int = 100


@dataclass(frozen=True)
class Stop(Message):
    TYPE: ClassVar = MsgType.STOP


@dataclass(frozen=True)
class QueryCal(Message):
    TYPE: ClassVar = MsgType.QUERY_CAL


@dataclass(frozen=True)
class ClearCal(Message):
    TYPE: ClassVar = MsgType.CLEAR_CAL
