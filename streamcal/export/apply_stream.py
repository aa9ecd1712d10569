"""``streamcal apply`` over a recording read in chunks: memory bounded by a chunk, output
identical to applying the calibration to the whole recording at once.

A magnetometer sample's covariates (accelerometer, temp, aux columns) are interpolated in time
between the rows where each column is sampled (:meth:`Track.covariates_at_mag`), so a sample
near a chunk's end may need a row of the next chunk. Rows are therefore held back until every
covariate column has a sample at or after them (``t < t_safe``: the earliest "last sample" over
the columns), and the rows before them that hold, per column, the last sample earlier than the
first held row are kept as context. Interpolating over context + held rows + new chunk then
gives each emitted sample exactly the brackets the whole recording gives it. A column that is
sampled rarely (or never) holds rows back until its next sample (or the end): memory then grows
towards the whole recording, the output stays the same.
"""
from __future__ import annotations

from typing import Callable, Iterable, Iterator

import numpy as np

from ..atomic import atomic_open
from .apply import Applied, apply_calibration, applied_columns, format_body, format_head

TIME = "t"
MAG = ("mx", "my", "mz")
ACCEL = ("ax", "ay", "az")


def _emit(track, start: int, stop: int, cal) -> Applied | None:
    """Apply ``cal`` to the magnetometer rows ``start:stop`` of ``track`` (covariates
    interpolated over all of ``track``)."""
    rows = track.mag_rows
    take = rows.copy()
    take[:start] = False
    take[stop:] = False
    if not take.any():
        return None
    pick = take[rows]                            # which of the mag samples
    cov = {k: v[pick] for k, v in track.covariates_at_mag().items()}
    accel = np.column_stack([cov[c] for c in ACCEL]) if all(c in cov for c in ACCEL) else None
    return apply_calibration(cal, track.t_mag[pick], track.mag[pick], cov, accel)


def _safe_end(track, start: int) -> int:
    """First row at or after ``start`` that may still need a later row (see module docstring)."""
    t = track.t
    t_safe = np.inf
    for name, values in track.columns.items():
        if name == TIME or name in MAG:
            continue
        sampled = np.flatnonzero(~np.isnan(values))
        t_safe = min(t_safe, t[sampled[-1]] if len(sampled) else -np.inf)
    return start + int(np.searchsorted(t[start:], t_safe, side="left"))


def _context_start(track, end: int) -> int:
    """First row to keep when rows ``end:`` are held: per covariate column, its last sample
    before ``t[end]`` (earlier ones no longer bracket anything)."""
    t = track.t
    keep = end
    for name, values in track.columns.items():
        if name == TIME or name in MAG:
            continue
        sampled = np.flatnonzero(~np.isnan(values[:end]) & (t[:end] < t[end]))
        if len(sampled):
            keep = min(keep, int(sampled[-1]))
    return keep


def applied_chunks(cal, chunks: Iterable, make_track: Callable) -> Iterator[Applied]:
    """:class:`Applied` pieces, in order, whose concatenation is ``apply`` of the whole
    recording. ``chunks``: consecutive Tracks of one recording; ``make_track(columns,
    metadata)`` builds a Track (passed in: this layer does not import the readers)."""
    carry, start = None, 0
    for chunk in chunks:
        if carry is None or not len(carry):
            carry, start = chunk, 0
        else:
            carry = make_track({n: np.concatenate([carry.columns[n], c])
                                for n, c in chunk.columns.items()}, chunk.metadata)
        end = _safe_end(carry, start)
        piece = _emit(carry, start, end, cal)
        if piece is not None:
            yield piece
        if end >= len(carry):
            carry, start = None, 0
            continue
        keep = _context_start(carry, end)
        carry = carry.select(slice(keep, len(carry)))
        start = end - keep
    if carry is not None:
        piece = _emit(carry, start, len(carry), cal)
        if piece is not None:
            yield piece


def write_applied_chunks(path, pieces: Iterable[Applied], metadata: Callable) -> int:
    """Write the pieces to ``path`` atomically, the head from ``metadata(first piece)`` (its
    ``heading`` entry depends on whether the pieces carry one); returns the samples written.
    An exception from ``pieces`` leaves ``path`` as it was."""
    written = 0
    with atomic_open(path, mode=0o644) as handle:
        for piece in pieces:
            if not written:
                handle.write(format_head(applied_columns(piece), metadata(piece)).encode())
            handle.write(format_body(piece).encode())
            written += len(piece.t)
    return written
