"""MotionCal-style ``Raw:`` captures (a serial log of ``Raw:ax,ay,az,gx,gy,gz,mx,my,mz`` lines)
→ Track, parsed by :class:`firmware_bridge.rawlines.RawLineReader` (the serial host's parser).

The lines carry no time: ``t`` is the sample number times ``period_s`` (default 0.01 s, the
100 Hz at which MotionCal sketches print), and the metadata says so. Units follow MotionCal's
fixed scales (:func:`firmware_bridge.rawlines.raw_to_si`): mag 0.1 µT/count, accel 1/8192 g,
gyro 1/16 °/s.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from firmware_bridge.rawlines import RawLineReader, raw_to_si

from ..errors import InputError
from .track import Track

DEFAULT_PERIOD_S = 0.01


def looks_like_raw_capture(text_head: str) -> bool:
    """True if a line of ``text_head`` starts with ``Raw:``."""
    return any(line.lstrip().startswith("Raw:") for line in text_head.splitlines())


def read_raw_capture(path, data: bytes, *, skip_bad_rows: bool = False,
                     period_s: float = DEFAULT_PERIOD_S) -> Track:
    """Track of the ``Raw:`` lines in ``data`` (the file's bytes, decompressed).

    Malformed ``Raw:`` lines raise :class:`InputError` naming the file and their count, unless
    ``skip_bad_rows``; lines of other kinds (``Uni:``, ``Cal1:``, banners) are skipped and counted.
    """
    reader = RawLineReader()
    counts = reader.feed(data if data.endswith(b"\n") else data + b"\n")
    stats = reader.stats
    bad = stats.bad_lines + stats.overlong
    if bad and not skip_bad_rows:
        raise InputError(f"{path}: {bad} malformed Raw: line(s) (expected nine int16 numbers "
                         "after 'Raw:'); --skip-bad-rows skips and counts them")
    if not len(counts):
        raise InputError(f"{path}: no valid Raw: lines")
    accel, gyro, mag = raw_to_si(counts)
    meta = {"sensor": "motioncal-raw", "source": f"Raw: capture {Path(path).name}",
            "input_format": "motioncal-raw", "mag_unit": "uT",
            "units": "counts x 0.1 uT (mag), /8192 g (accel), /16 deg/s (gyro): MotionCal's scales",
            "time": f"Raw: lines carry no time stamps; t = sample number x {period_s:g} s "
                    "(assumed rate)",
            "raw_lines": str(stats.lines), "other_lines_skipped": str(stats.other_lines)}
    if bad:
        meta["bad_lines_skipped"] = str(bad)
    t = np.arange(len(counts)) * float(period_s)
    track = Track.from_arrays(t, mag=mag, accel=accel, gyro=gyro, metadata=meta)
    track.skipped_rows = bad
    return track
