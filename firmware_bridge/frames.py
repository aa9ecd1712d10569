"""The serial frame codec shared with the Arduino sketch (see ``PROTOCOL.md``).

Wire format of one frame::

    COBS( header | body | crc16 ) 0x00
    header = version:u8  type:u8  seq:u16          (little-endian, like every field)
    crc16  = CRC-16/CCITT-FALSE over header|body, u16 little-endian

The decoded payload is at most :data:`MAX_PAYLOAD` = 253 bytes, so a COBS frame never needs a
0xFF block and the sketch can encode in place. Decoding is a pure function of bytes
(:class:`FrameDecoder`): damaged input is counted in :class:`DecoderStats`, never raised, and
the decoder resynchronises at the next 0x00 with a bounded buffer.
"""
from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np
from cobs import cobs

from .messages import *  # noqa: F401,F403  (the codec's callers use fr.Hello, fr.MsgType, …)
from .messages import (crc16, Ack, CalReport, CalSample, ClearCal, GetInfo, Hello, Message, MsgType,
                       Nak, QueryCal, Sample, SetCalibration, SphereSums, Start, Stop)
from .selfcal_frames import SelfCal

PROTOCOL_VERSION = 1
DELIMITER = b"\x00"
HEADER = struct.Struct("<BBH")
CRC = struct.Struct("<H")
#: Largest decoded payload (header + body + CRC), bytes: keeps every frame a single COBS block.
MAX_PAYLOAD = 253
#: Largest encoded frame without its delimiter, bytes; the decoder's buffer bound.
MAX_ENCODED = MAX_PAYLOAD + 1



MESSAGES: dict[int, type[Message]] = {cls.TYPE: cls for cls in (
    Hello, Sample, CalSample, SphereSums, CalReport, Ack, Nak, GetInfo, Start, Stop,
    SetCalibration, QueryCal, ClearCal, SelfCal)}
BOARD_TO_HOST = frozenset(t for t in MESSAGES if t < 0x10)


# -- frames ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """One decoded frame: ``seq`` the sender's 16-bit counter, ``msg`` the typed message."""

    seq: int
    msg: Message
    version: int = PROTOCOL_VERSION

    @property
    def type(self) -> MsgType:
        return self.msg.TYPE


def encode_payload(msg: Message, seq: int) -> bytes:
    """header | body | crc16 (before COBS)."""
    data = HEADER.pack(PROTOCOL_VERSION, int(msg.TYPE), seq & 0xFFFF) + msg.pack_body()
    return data + CRC.pack(crc16(data))


def encode(msg: Message, seq: int) -> bytes:
    """The complete wire frame of ``msg`` with sequence number ``seq``, delimiter included."""
    return cobs.encode(encode_payload(msg, seq)) + DELIMITER


class FrameError(ValueError):
    """Why one payload was rejected; ``kind`` names the :class:`DecoderStats` counter."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


def decode_payload(payload: bytes) -> Frame:
    """Check and parse one COBS-decoded payload; raise :class:`FrameError` if it is damaged."""
    if len(payload) < HEADER.size + CRC.size:
        raise FrameError("truncated", f"{len(payload)}-byte payload is shorter than header + CRC")
    data, (crc,) = payload[:-CRC.size], CRC.unpack(payload[-CRC.size:])
    if crc16(data) != crc:
        raise FrameError("crc_errors", "CRC mismatch")
    version, mtype, seq = HEADER.unpack(data[:HEADER.size])
    if version != PROTOCOL_VERSION:
        raise FrameError("malformed", f"protocol version {version}, expected {PROTOCOL_VERSION}")
    cls = MESSAGES.get(mtype)
    if cls is None:
        raise FrameError("malformed", f"unknown message type 0x{mtype:02x}")
    body = data[HEADER.size:]
    if len(body) != cls.body_size():
        raise FrameError("malformed", f"{cls.__name__} body is {len(body)} bytes, expected {cls.body_size()}")
    return Frame(seq=seq, msg=cls.unpack_body(body), version=version)


@dataclass
class DecoderStats:
    """Counters of a :class:`FrameDecoder`; every byte fed ends up in a frame or in garbage."""

    frames: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    truncated: int = 0
    oversized: int = 0
    malformed: int = 0
    garbage_bytes: int = 0

    @property
    def rejected(self) -> int:
        return self.crc_errors + self.cobs_errors + self.truncated + self.oversized + self.malformed

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class FrameDecoder:
    """Bytes in, frames out: ``decoder.feed(chunk) -> list[Frame]``.

    Pure (no I/O); memory is bounded by ``max_encoded`` bytes. A frame longer than that is
    dropped up to the next delimiter and counted as ``oversized``; empty frames (consecutive
    delimiters, used to flush a receiver) are ignored.
    """

    def __init__(self, max_encoded: int = MAX_ENCODED):
        self.max_encoded = max_encoded
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        parts = bytes(data).split(DELIMITER)
        for part in parts[:-1]:
            if self._discarding:
                self.stats.garbage_bytes += len(part) + 1
                self._discarding = False
            else:
                self._buf += part
                self._finish(out)
            self._buf.clear()
        self._append(parts[-1])
        return out

    @property
    def buffered(self) -> int:
        """Bytes waiting for their delimiter (≤ ``max_encoded``)."""
        return len(self._buf)

    def _append(self, part: bytes) -> None:
        if self._discarding:
            self.stats.garbage_bytes += len(part)
            return
        if len(self._buf) + len(part) > self.max_encoded:
            self.stats.oversized += 1
            self.stats.garbage_bytes += len(self._buf) + len(part)
            self._buf.clear()
            self._discarding = True
            return
        self._buf += part

    def _finish(self, out: list[Frame]) -> None:
        if not self._buf:
            return
        if len(self._buf) > self.max_encoded:
            self.stats.oversized += 1
            self.stats.garbage_bytes += len(self._buf) + 1
            return
        try:
            frame = decode_payload(cobs.decode(bytes(self._buf)))
        except cobs.DecodeError:
            self.stats.cobs_errors += 1
        except FrameError as exc:
            setattr(self.stats, exc.kind, getattr(self.stats, exc.kind) + 1)
        else:
            self.stats.frames += 1
            out.append(frame)
            return
        self.stats.garbage_bytes += len(self._buf) + 1


class SequenceCounter:
    """Counts frames lost from gaps in a sender's 16-bit sequence numbers.

    ``observe(seq)`` returns how many frames were missed just before this one. A gap is taken
    modulo 2**16, so more than 65535 consecutive losses alias (at 115200 baud that is > 3 min
    of silence); :meth:`reset` after a HELLO (the board rebooted and restarted at 0).
    """

    def __init__(self):
        self.expected: int | None = None
        self.received = 0
        self.lost = 0

    def observe(self, seq: int) -> int:
        gap = 0 if self.expected is None else (seq - self.expected) & 0xFFFF
        self.expected = (seq + 1) & 0xFFFF
        self.received += 1
        self.lost += gap
        return gap

    def reset(self) -> None:
        self.expected = None
