"""Asynchronous sensor streams merged into one track (docs/tracks_and_inputs.md rows carrying only
some columns).

An autopilot log holds each message type at its own rate (MAG ~10 Hz, IMU 25–50 Hz, RCOU…).
Rather than resample, every message becomes its own row: the row carries the columns of its
stream and leaves the others empty (NaN), which is exactly what docs/tracks_and_inputs.md allows.
Rows are put in
time order with a stable sort, so equal stamps keep the order in which the streams were given.

    streams = [Stream("MAG", t_mag, {"mx": .., "my": .., "mz": ..}),
               Stream("IMU", t_imu, {"ax": .., ..., "gz": ..})]
    track = merge(streams, metadata)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputError
from .track import Track
from .trackio import ACCEL, GYRO, MAG, TEMP


@dataclass
class Stream:
    """One message type: ``t`` (n,) seconds and ``columns`` ``{track column: (n,)}``."""

    name: str
    t: np.ndarray
    columns: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        self.columns = {k: np.asarray(v, dtype=np.float64).reshape(-1)
                        for k, v in self.columns.items()}
        for name, values in self.columns.items():
            if len(values) != len(self.t):
                raise InputError(f"stream {self.name}: column {name} has {len(values)} values "
                                 f"for {len(self.t)} time stamps")


def merge(streams: Sequence[Stream], metadata: Mapping[str, str], *,
          t0: float | None = None, names: Sequence[str] | None = None) -> Track:
    """Stack the streams' rows into one track, time ordered, ``t`` shifted so it starts at
    ``t0`` (default: the earliest stamp of any stream) = 0 s.

    Streams with no rows are left out; a column named by several streams is shared; ``names``
    (default: the streams' columns) are the columns the track has, empty where no stream fills
    them. Raises :class:`InputError` if no stream has a row.
    """
    streams = [s for s in streams if len(s.t)]
    if not streams:
        raise InputError("no samples to build a track from")
    t = np.concatenate([s.t for s in streams])
    if t0 is None:
        t0 = float(t.min())
    if names is None:
        names = list(dict.fromkeys(name for s in streams for name in s.columns))
    n = len(t)
    columns = {name: np.full(n, np.nan) for name in names}
    start = 0
    for s in streams:
        stop = start + len(s.t)
        for name, values in s.columns.items():
            columns[name][start:stop] = values
        start = stop
    order = np.argsort(t, kind="stable")
    t = t[order] - t0
    for name in names:   # one column at a time: the unsorted one is freed at once
        columns[name] = columns[name][order]

    def triple(names3):
        if names3[0] not in columns:
            return None
        return tuple(columns.pop(c) for c in names3)

    mag, accel, gyro = triple(MAG), triple(ACCEL), triple(GYRO)
    temp = columns.pop(TEMP, None)
    # the arrays were made for this track: no copies (a long log's track is most of the memory)
    return Track._from_arrays(t, mag, accel, gyro, temp, columns, metadata, copy=False)


def drop_nonfinite(streams: Sequence[Stream], meta: dict) -> list[Stream]:
    """The streams without rows whose time or any value is NaN or infinite (damaged bytes of a
    log decode to such values); the rows dropped are counted in ``meta["read_warnings"]``."""
    out, dropped = [], []
    for s in streams:
        ok = np.isfinite(s.t)
        for values in s.columns.values():
            ok &= np.isfinite(values)
        if not ok.all():
            dropped.append(f"{int((~ok).sum())} {s.name}")
            s = Stream(s.name, s.t[ok], {k: v[ok] for k, v in s.columns.items()})
        out.append(s)
    if dropped:
        note = "dropped rows with non-finite values (damaged bytes): " + ", ".join(dropped)
        meta["read_warnings"] = "; ".join(filter(None, (meta.get("read_warnings"), note)))
    return out
