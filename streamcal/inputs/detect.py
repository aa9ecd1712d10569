"""Which reader a recording needs, decided from its content (magic bytes, first lines), not
from its name. A ROS 2 bag is a directory: recognised by the ``metadata.yaml`` in it."""
from __future__ import annotations

import gzip
import zlib
from pathlib import Path

from ..errors import InputError
from .dataflash import looks_like_dataflash
from .raw_capture import looks_like_raw_capture
from .rosbag import is_rosbag2_dir, looks_like_rosbag1, looks_like_rosbag2_file
from .ulog import looks_like_ulog

HEAD_BYTES = 1 << 16
FORMATS = ("dataflash", "ulog", "rosbag1", "rosbag2", "track", "raw", "csv")
_GZIP_MAGIC = b"\x1f\x8b"
_TRACK_COLUMNS = {"t", "mx", "my", "mz"}


def read_head(path: Path) -> bytes:
    """The first :data:`HEAD_BYTES` bytes of the (gzip-decompressed) file."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(HEAD_BYTES)
            if head[:2] != _GZIP_MAGIC:
                return head
        with gzip.open(path, "rb") as handle:
            return handle.read(HEAD_BYTES)
    except (EOFError, OSError, zlib.error) as exc:
        if isinstance(exc, OSError) and not isinstance(exc, gzip.BadGzipFile) and exc.strerror:
            raise InputError(f"{path}: cannot read the file ({exc.strerror})") from None
        raise InputError(f"{path}: damaged gzip file ({exc})") from None


def detect(path) -> str:
    """One of :data:`FORMATS`: ``dataflash`` (ArduPilot .bin), ``ulog`` (PX4 .ulg), ``rosbag1``
    (ROS 1 .bag), ``rosbag2`` (ROS 2 bag directory, or its sqlite3/MCAP storage file), ``track``
    (docs/tracks_and_inputs.md CSV), ``raw`` (MotionCal ``Raw:`` lines) or ``csv`` (other
    delimited text)."""
    path = Path(path)
    if path.is_dir():
        if is_rosbag2_dir(path):
            return "rosbag2"
        raise InputError(f"{path}: a directory, not a recording (a ROS 2 bag directory holds a "
                         "metadata.yaml)")
    head = read_head(path)
    if not head:
        raise InputError(f"{path}: empty file")
    if looks_like_dataflash(head):
        return "dataflash"
    if looks_like_ulog(head):
        return "ulog"
    if looks_like_rosbag1(head):
        return "rosbag1"
    if looks_like_rosbag2_file(head):
        return "rosbag2"
    text = head.decode("utf-8", errors="replace")
    if looks_like_raw_capture(text):
        return "raw"
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("# streamcal-track"):
            return "track"
        if stripped and not stripped.startswith("#"):
            names = {c.strip().strip('"') for c in stripped.split(",")}
            return "track" if _TRACK_COLUMNS <= names else "csv"
    return "track"  # only comments: let the track reader say what is missing


def read_whole(path) -> bytes:
    """All bytes of the (gzip-decompressed) file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        return gzip.decompress(raw) if raw[:2] == _GZIP_MAGIC else raw
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    except (EOFError, zlib.error) as exc:
        raise InputError(f"{path}: damaged gzip file ({exc})") from None
