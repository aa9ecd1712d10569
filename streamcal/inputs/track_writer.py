"""A track file written chunk by chunk (docs/tracks_and_inputs.md), atomically: memory bounded by
one chunk.

The bytes are those :func:`streamcal.inputs.trackio.write` writes for the concatenated chunks
(same head, same cells; for ``.gz`` the member :func:`gzip.compress` writes at level 6 with
``mtime=0``), so a chunked ``convert`` and a whole-file one give identical
files.
"""
from __future__ import annotations

import contextlib
import os
import zlib
from pathlib import Path
from typing import Iterator

from ..atomic import atomic_open
from . import trackio


@contextlib.contextmanager
def track_writer(path: str | os.PathLike) -> Iterator:
    """``with track_writer(path) as write: write(track)`` for each chunk (a Track), in order.

    The first call writes the head from that chunk's columns and metadata; later chunks must
    have the same columns. ``path`` is replaced only when the block ends without an exception;
    a chunk with no rows writes nothing. Gzip-compressed when the name ends in ``.gz``.
    """
    with atomic_open(path, mode=0o644) as handle:
        packed = _GzipMember(handle) if Path(path).name.endswith(".gz") else None
        put = packed.write if packed else handle.write
        names: list[str] | None = None

        def write(track) -> None:
            nonlocal names
            if names is None:
                names = list(track.columns)
                put(trackio.format_head(names, track.metadata).encode("utf-8"))
            elif list(track.columns) != names:
                raise ValueError(f"chunk columns {list(track.columns)} differ from {names}")
            if len(track):
                put(trackio.format_rows(track.columns).encode("utf-8"))

        yield write
        if packed:
            packed.close()


class _GzipMember:
    """One gzip member written in pieces: what ``gzip.compress(data, 6, mtime=0)`` writes for the
    concatenated pieces (it is ``zlib.compress(data, 6, wbits=31)``; deflate without flushes
    does not depend on how its input was cut)."""

    def __init__(self, handle):
        self.handle = handle
        self.deflate = zlib.compressobj(6, zlib.DEFLATED, 31)

    def write(self, data: bytes) -> None:
        self.handle.write(self.deflate.compress(data))

    def close(self) -> None:
        self.handle.write(self.deflate.flush())
