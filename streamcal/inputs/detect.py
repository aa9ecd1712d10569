"""Which reader a recording needs, decided from its content (magic bytes, first lines), not
from its name."""
from __future__ import annotations

import gzip
import zlib
from pathlib import Path

from ..errors import InputError
from .dataflash import looks_like_dataflash
from .raw_capture import looks_like_raw_capture
from .ulog import looks_like_ulog

HEAD_BYTES = 1 << 16
FORMATS = ("dataflash", "ulog", "track", "raw", "csv")
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
    """One of :data:`FORMATS`: ``dataflash`` (ArduPilot .bin), ``ulog`` (PX4 .ulg), ``track``
    (docs/tracks_and_inputs.md CSV), ``raw`` (MotionCal ``Raw:`` lines) or ``csv`` (other
    delimited text)."""
    path = Path(path)
    head = read_head(path)
    if not head:
        raise InputError(f"{path}: empty file")
    if looks_like_dataflash(head):
        return "dataflash"
    if looks_like_ulog(head):
        return "ulog"
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
