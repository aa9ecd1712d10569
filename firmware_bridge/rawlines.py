"""Reader for the ``Raw:`` text lines that MotionCal-style sketches print.

Format (PJRC MotionCal, ``rawdata.c``: ``data[0..2]`` accel, ``[3..5]`` gyro, ``[6..8]`` mag)::

    Raw:ax,ay,az,gx,gy,gz,mx,my,mz\\r\\n        nine decimal int16 counts

with MotionCal's fixed scales (``imuread.h``: ``G_PER_COUNT 1/8192``, ``DEG_PER_SEC_PER_COUNT
1/16``, ``UT_PER_COUNT 0.1``): accel counts/8192 g, gyro counts/16 °/s, mag counts/10 µT.
Other lines of those sketches (``Uni:``, ``Cal1:``, ``Cal2:``, banners) are counted and skipped.
Like :class:`~firmware_bridge.frames.FrameDecoder`, the reader is a pure function of bytes with a
bounded line buffer.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from streamcal.constants import GRAVITY

PREFIX = b"Raw:"
G_PER_COUNT = 1.0 / 8192.0
DEG_PER_SEC_PER_COUNT = 1.0 / 16.0
UT_PER_COUNT = 0.1
STANDARD_GRAVITY = GRAVITY  # m/s² per g
#: Longest line kept (bytes); nine int16 fields need at most 4 + 9 × 7 = 67.
MAX_LINE = 128


@dataclass
class RawLineStats:
    lines: int = 0          # good Raw: lines
    bad_lines: int = 0      # Raw: lines that are not nine int16 numbers
    other_lines: int = 0    # lines of other kinds (skipped)
    overlong: int = 0       # lines longer than MAX_LINE (dropped)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class RawLineReader:
    """Bytes in, ``(n, 9)`` int64 counts out (``ax ay az gx gy gz mx my mz``), per complete line."""

    def __init__(self, max_line: int = MAX_LINE):
        self.max_line = max_line
        self.stats = RawLineStats()
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> np.ndarray:
        rows = []
        parts = bytes(data).split(b"\n")
        for part in parts[:-1]:
            if self._discarding:
                self._discarding = False
            else:
                self._buf += part
                row = self._parse(bytes(self._buf).strip())
                if row is not None:
                    rows.append(row)
            self._buf.clear()
        if not self._discarding:
            if len(self._buf) + len(parts[-1]) > self.max_line:
                self.stats.overlong += 1
                self._buf.clear()
                self._discarding = True
            else:
                self._buf += parts[-1]
        return np.array(rows, dtype=np.int64).reshape(-1, 9)

    def _parse(self, line: bytes):
        if not line:
            return None
        if not line.startswith(PREFIX):
            self.stats.other_lines += 1
            return None
        try:
            row = [int(v) for v in line[len(PREFIX):].split(b",")]
        except ValueError:
            row = []
        if len(row) != 9 or not all(-32768 <= v <= 32767 for v in row):
            self.stats.bad_lines += 1
            return None
        self.stats.lines += 1
        return row


def raw_to_si(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(n,9)`` MotionCal counts → accel (n,3) m/s², gyro (n,3) rad/s, mag (n,3) µT."""
    counts = np.asarray(counts, dtype=float).reshape(-1, 9)
    accel = counts[:, 0:3] * (G_PER_COUNT * STANDARD_GRAVITY)
    gyro = counts[:, 3:6] * (DEG_PER_SEC_PER_COUNT * math.pi / 180.0)
    mag = counts[:, 6:9] * UT_PER_COUNT
    return accel, gyro, mag
