"""Track files read in chunks (docs/tracks_and_inputs.md): memory bounded by the chunk, not the
recording.

:func:`iter_track_chunks` decompresses and parses a ``.csv`` / ``.csv.gz`` track incrementally
and yields one :class:`~streamcal.inputs.track.Track` per chunk of at most ``rows`` physical lines.
It applies the same rules, through the same functions, as :func:`streamcal.inputs.trackio.read`
(metadata, header, cells, partial triples, time going backwards — also across chunk boundaries)
and raises the same :class:`~streamcal.errors.TrackError` naming file, physical line and column;
an error is raised when the chunk holding it is reached, after the chunks before it were yielded.
One difference follows: a truncated or damaged gzip stream is found where it ends, so a bad line
before the damage is reported first (the whole-file reader reports the damage).
"""
from __future__ import annotations

import gzip
import os
import zlib
from typing import Iterator

import numpy as np

from ..errors import TrackError
from . import trackio
from .track import Track

#: Bytes read from the file (after decompression) per read call.
READ_BYTES = 1 << 20


def _raw_pieces(where: str) -> Iterator[bytes]:
    """The file's (decompressed) bytes, in pieces of about :data:`READ_BYTES`."""
    try:
        handle = open(where, "rb")
    except OSError as exc:
        raise TrackError(f"cannot read the file: {exc.strerror or exc}", where) from None
    with handle:
        gz = handle.read(2) == trackio._GZIP_MAGIC
        handle.seek(0)
        stream = gzip.GzipFile(fileobj=handle, mode="rb") if gz else handle
        while True:
            try:
                piece = stream.read(READ_BYTES)
            except EOFError:
                raise TrackError("gzip stream ends early (truncated or damaged file)",
                                 where) from None
            except (zlib.error, ValueError) as exc:
                raise TrackError(f"damaged gzip file: {exc}", where) from None
            except OSError as exc:
                if gz:
                    raise TrackError(f"damaged gzip file: {exc}", where) from None
                raise TrackError(f"cannot read the file: {exc.strerror or exc}", where) from None
            if not piece:
                return
            yield piece


def _line_pieces(where: str, rows: int) -> Iterator[bytes]:
    """Whole lines, at most ``rows`` of them per piece (the last piece may lack its newline).
    Splitting at newlines never cuts a UTF-8 character."""
    buffer = b""
    for piece in _raw_pieces(where):
        buffer += piece
        ends = np.flatnonzero(np.frombuffer(buffer, dtype=np.uint8) == 10)
        start = 0
        for k in range(rows - 1, len(ends), rows):
            yield buffer[start:ends[k] + 1]
            start = ends[k] + 1
        buffer = buffer[start:]
    if buffer:
        yield buffer


def iter_track_chunks(path: str | os.PathLike, rows: int = 100_000,
                      skip_bad_rows: bool = False) -> Iterator[Track]:
    """Yield the track at ``path`` as consecutive :class:`Track` s of at most ``rows`` rows.

    Every chunk carries the file's metadata and path, and ``lines`` (the physical line of each
    row in the file). With ``skip_bad_rows`` each chunk counts its own ``skipped_rows``; a chunk
    whose rows were all bad is yielded empty so its count is not lost. Raises
    :class:`TrackError` exactly where :func:`streamcal.inputs.trackio.read` would, except that
    the error comes once the chunks before it were consumed.
    """
    if int(rows) < 1:
        raise ValueError(f"rows must be a positive number, got {rows}")
    where = os.fspath(path)
    pieces = _line_pieces(where, int(rows))
    text, at_end = "", False
    # the preamble: read on until the header line is complete (or the file ends)
    while True:
        try:
            text += trackio._decode(next(pieces))
        except StopIteration:
            at_end = True
        try:
            metadata, header_index, names, body = trackio.parse_preamble(text, where)
        except TrackError as exc:
            if at_end or exc.line is not None:
                raise
            continue
        if at_end or body or text.endswith("\n"):
            break
    first_line = header_index + 2
    n_rows = n_skipped = 0
    t_before, first_reason = None, None
    time_col = names.index(trackio.TIME)
    while True:
        if body:
            values, numbers, skipped, reasons = trackio.parse_rows(
                body, first_line, names, where, skip_bad_rows, t_before)
            first_line += body.count("\n") + (not body.endswith("\n"))
            n_rows, n_skipped = n_rows + len(numbers), n_skipped + skipped
            first_reason = first_reason or (reasons[0] if reasons else None)
            if len(values):
                t_before = max(float(np.max(values[:, time_col])),
                               -np.inf if t_before is None else t_before)
            if len(values) or skipped:
                yield Track({name: np.ascontiguousarray(values[:, j])
                             for j, name in enumerate(names)}, metadata, where, numbers,
                            skipped, reasons)
        if at_end:
            break
        try:
            body = trackio._decode(b"\n" + next(pieces))[1:]   # a BOM only counts at the start
        except StopIteration:
            at_end, body = True, ""
    if not n_rows and not n_skipped:
        raise TrackError("no data rows after the header", where, header_index + 1)
    if not n_rows:
        raise TrackError(f"no valid data rows: all {n_skipped} rows are bad; first: "
                         f"{first_reason}", where)


def iter_track_blocks(chunks: Iterator[Track], n: int) -> Iterator:
    """Re-cut the chunks of :func:`iter_track_chunks` into
    :class:`streamcal.samples.SampleBlock` s of exactly ``n`` rows (the last may be shorter):
    the blocks ``Track.read(path).blocks(n)`` gives, with one chunk (plus < ``n`` rows) in memory."""
    left: Track | None = None
    for chunk in chunks:
        if left is not None and len(left):
            chunk = Track({name: np.concatenate([left.columns[name], col])
                           for name, col in chunk.columns.items()}, chunk.metadata, chunk.path,
                          np.concatenate([left.lines, chunk.lines]))
        whole = len(chunk) - len(chunk) % n
        if whole:
            yield from chunk.select(slice(0, whole)).blocks(n)
        left = chunk.select(slice(whole, len(chunk)))
    if left is not None and len(left):
        yield from left.blocks(n)
