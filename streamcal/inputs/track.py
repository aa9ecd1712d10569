"""Track: a recorded log as columns of float64 samples (docs/tracks_and_inputs.md).

    track = Track.read("log.csv.gz")            # TrackError names file, line and column
    track.mag, track.t_mag                        # (M,3) in track.mag_unit, (M,) s
    cov = track.covariates_at_mag()               # {"temp": (M,), "ax": (M,), ...}
    for block in track.blocks(256): ...           # firmware_bridge SampleBlocks

Every column is an (N,) float64 array over all rows, NaN where the cell was empty ("not sampled
at this instant"): sensors run at different rates, so a row may carry only IMU columns, only the
magnetometer, or both. ``t`` is present on every row and non-decreasing. Arrays are read-only;
derive new tracks with :meth:`Track.select` or :meth:`Track.from_arrays`.
"""
from __future__ import annotations

import os
import re
from functools import cached_property
from pathlib import Path
from typing import Iterable, Iterator, Mapping

import numpy as np

from . import trackio
from ..constants import ATTITUDE_COLUMNS
from ..errors import InputError, TrackError
from ..samples import SampleBlock
from ..units import UNKNOWN
from .trackio import ACCEL, GYRO, KNOWN, MAG, TEMP, TIME, TRIPLES

_UNIT_ALIASES = {"ut": "uT", "µt": "uT", "μt": "uT", "microtesla": "uT", "m/s^2": "m/s^2",
                 "m/s²": "m/s^2", "m/s2": "m/s^2"}


#: Units a track may declare; anything else (``probably uT``, ``unknown (normalized?)``) is
#: :data:`~streamcal.units.UNKNOWN`, its words kept in the metadata.
_KNOWN_UNITS = {"uT", "nT", "mG", "G", "counts", "m/s^2", "g", "mg"}


def _unit(text: str | None, default: str) -> str:
    """The unit of a ``# mag_unit: counts (0.15 uT/LSB)`` line: the words before any remark;
    ``unknown`` when they name no unit streamcal knows."""
    if text is None:
        return default
    unit = re.split(r"[(;]", text, maxsplit=1)[0].strip()
    unit = _UNIT_ALIASES.get(unit.lower(), unit) or default
    return unit if unit in _KNOWN_UNITS else UNKNOWN


def _readonly(values: np.ndarray) -> np.ndarray:
    values.flags.writeable = False
    return values


class Track:
    """Columnar samples of one recording.

    Attributes:
        columns: ``{name: (N,) float64}`` in file order, NaN for empty cells.
        metadata: ``{key: value}`` from the ``# key: value`` lines, in file order.
        path: the file it was read from, or None.
        lines: (N,) int64 physical line (1-based) of each row in that file; 0 if not from a file.
        skipped_rows: rows dropped by ``skip_bad_rows=True``; ``skip_reasons`` the first few why.
    """

    def __init__(self, columns: Mapping[str, np.ndarray], metadata: Mapping[str, str] | None = None,
                 path: str | os.PathLike | None = None, lines: np.ndarray | None = None,
                 skipped_rows: int = 0, skip_reasons: Iterable[str] = ()):
        self.columns = {name: _readonly(np.asarray(col, dtype=np.float64))
                        for name, col in columns.items()}
        self.metadata = dict(metadata or {})
        self.path = Path(path) if path is not None else None
        n = len(self.columns[TIME])
        self.lines = _readonly(np.zeros(n, dtype=np.int64) if lines is None
                               else np.asarray(lines, dtype=np.int64))
        self.skipped_rows = int(skipped_rows)
        self.skip_reasons = list(skip_reasons)

    # ------------------------------------------------------------------ construction

    @classmethod
    def read(cls, path: str | os.PathLike, skip_bad_rows: bool = False) -> "Track":
        """Read a ``.csv`` or ``.csv.gz`` track (gzip recognised by its magic bytes).

        Raises :class:`TrackError` (file, 1-based line, column) on any violation of the track format
        (docs/tracks_and_inputs.md).
        With ``skip_bad_rows`` rows with bad cells, partial samples or backwards time are
        dropped and counted instead; structural problems (no header, missing columns, damaged
        gzip) still raise.
        """
        parsed = trackio.read(path, skip_bad_rows=skip_bad_rows)
        return cls(parsed.columns, parsed.metadata, path, parsed.lines, parsed.skipped_rows,
                   parsed.skip_reasons)

    @classmethod
    def from_arrays(cls, t, mag=None, accel=None, gyro=None, temp=None, aux=None,
                    metadata=None) -> "Track":
        """Build a track from arrays (NaN = not sampled).

        Args:
            t: (N,) seconds, finite, non-decreasing.
            mag: (N,3) in the track's mag unit (µT unless ``metadata["mag_unit"]`` says else);
                None gives all-empty mx,my,mz columns.
            accel: (N,3) m/s²; gyro: (N,3) rad/s; temp: (N,) °C; aux: ``{name: (N,)}``.
            metadata: ``{key: value}`` strings, written as ``# key: value`` lines.
        """
        return cls._from_arrays(t, mag, accel, gyro, temp, aux, metadata, copy=True)

    @classmethod
    def _from_arrays(cls, t, mag, accel, gyro, temp, aux, metadata, *, copy: bool) -> "Track":
        """:meth:`from_arrays`; ``copy=False`` keeps the given float64 arrays (a triple may
        then be a tuple of three (N,) columns), for readers that built them for the track."""
        def own(values):
            return np.array(values, dtype=np.float64, copy=True) if copy else \
                np.asarray(values, dtype=np.float64)

        t = own(t)
        if t.ndim != 1:
            raise TrackError(f"t must be 1-D, got shape {t.shape}", column=TIME)
        n = len(t)
        columns = {TIME: t}
        triples = {"accel": accel, "gyro": gyro, "mag": mag}
        for kind in ("accel", "gyro", "mag"):
            values = triples[kind]
            if values is None and kind != "mag":
                continue
            if isinstance(values, tuple):     # three columns, kept as they are
                columns.update(zip(TRIPLES[kind], (own(v) for v in values)))
                continue
            values = np.full((n, 3), np.nan) if values is None else own(values)
            if values.shape != (n, 3):
                raise TrackError(f"{kind} must have shape ({n}, 3), got {values.shape}",
                                 column=TRIPLES[kind][0])
            columns.update(zip(TRIPLES[kind], values.T.copy()))
        if temp is not None:
            columns[TEMP] = own(temp)
        for name, values in dict(aux or {}).items():
            if name in KNOWN or not trackio.COLUMN_NAME.fullmatch(str(name)):
                raise TrackError(f"invalid auxiliary column name {name!r}", column=str(name))
            columns[str(name)] = own(values)
        for name, values in columns.items():
            if values.shape != (n,):
                raise TrackError(f"must have shape ({n},), got {values.shape}", column=name)
        _validate(columns)
        return cls(columns, trackio.check_metadata(metadata))

    @classmethod
    def from_blocks(cls, blocks: Iterable, metadata=None) -> "Track":
        """Concatenate :class:`streamcal.samples.SampleBlock` s (inverse of :meth:`blocks`).

        Sensors missing from some blocks are NaN there. ``metadata`` defaults to the blocks'
        ``source``.
        """
        blocks = list(blocks)
        if not blocks:
            raise InputError("no sample blocks to build a track from")
        sizes = [len(b) for b in blocks]

        def stack(get, width):
            if all(get(b) is None for b in blocks):
                return None
            shape = (lambda k: (k, width)) if width else (lambda k: (k,))
            return np.concatenate([np.full(shape(k), np.nan) if get(b) is None
                                   else np.asarray(get(b), dtype=np.float64).reshape(shape(k))
                                   for b, k in zip(blocks, sizes)])

        names = list(dict.fromkeys(name for b in blocks for name in b.aux))
        aux = {name: stack(lambda b, nm=name: b.aux.get(nm), 0) for name in names}
        if metadata is None:
            sources = list(dict.fromkeys(b.source for b in blocks if b.source))
            metadata = {"source": sources[0]} if len(sources) == 1 else {}
        return cls.from_arrays(stack(lambda b: b.t, 0), mag=stack(lambda b: b.mag, 3),
                               accel=stack(lambda b: b.accel, 3), gyro=stack(lambda b: b.gyro, 3),
                               temp=stack(lambda b: b.temp, 0), aux=aux, metadata=metadata)

    def write(self, path: str | os.PathLike) -> None:
        """Write atomically as CSV (``.csv.gz``: gzip); floats round-trip exactly."""
        trackio.write(path, self.columns, self.metadata)

    def select(self, rows) -> "Track":
        """A sub-track of the rows picked by a bool (N,) mask, an index array or a slice."""
        if not isinstance(rows, slice):
            rows = np.asarray(rows)
            if rows.dtype == bool and rows.shape != (len(self),):
                raise InputError(f"row mask must have shape ({len(self)},), got {rows.shape}")
            if rows.dtype != bool and len(rows) > 1 and np.any(np.diff(rows) < 0):
                raise InputError("row indices must be increasing (t must stay non-decreasing)")
        return Track({name: col[rows] for name, col in self.columns.items()}, self.metadata,
                     self.path, self.lines[rows])

    def keep_aux(self, names: Iterable[str]) -> "Track":
        """The same track with only the auxiliary channels ``names`` (every other column kept)."""
        keep = set(names)
        drop = [n for n in self.aux_names if n not in keep]
        return Track({n: c for n, c in self.columns.items() if n not in drop}, self.metadata,
                     self.path, self.lines, self.skipped_rows, self.skip_reasons)

    # ------------------------------------------------------------------ access

    def __len__(self) -> int:
        return len(self.columns[TIME])

    def __repr__(self) -> str:
        name = self.path.name if self.path else "arrays"
        return (f"Track({name!r}, {len(self)} rows, {int(self.mag_rows.sum())} mag samples "
                f"in {self.mag_unit}, columns {','.join(self.columns)})")

    def _repr_html_(self) -> str:
        """Jupyter's view: file, rows and samples per sensor, duration, columns, units; every
        text escaped."""
        from ..units import display_unit, quantity
        from ..values import html_table

        t = self.t
        span = float(t[-1] - t[0]) if len(t) else 0.0
        sensors = ", ".join(f"{int(self._rows(k).sum())} {k}" for k in ("mag", "accel", "gyro")
                            if self.has(k))
        rows = [("file", self.path.name if self.path else "(arrays)"),
                ("samples", f"{len(self)} rows" + (f": {sensors}" if sensors else "")),
                ("duration", quantity(span, "s", 4)),
                ("columns", ", ".join(self.columns)),
                ("units", ", ".join(["t s"] + [
                    f"{k} {u}" for k, u in (("mag", display_unit(self.mag_unit) or "unknown"),
                                            ("accel", display_unit(self.accel_unit) or "unknown"),
                                            ("gyro", "rad/s"), ("temp", "°C"))
                    if self.has(k)]))]
        if self.skipped_rows:
            rows.append(("skipped rows", self.skipped_rows))
        return html_table(rows, caption="Track")

    @property
    def t(self) -> np.ndarray:
        """(N,) time of every row, seconds."""
        return self.columns[TIME]

    def has(self, name: str) -> bool:
        """True if column ``name`` (or sensor ``"mag"``/``"accel"``/``"gyro"``) has any sample."""
        if name in TRIPLES:
            return bool(self._rows(name).any())
        return name in self.columns and bool(np.isfinite(self.columns[name]).any())

    def _rows(self, kind: str) -> np.ndarray:
        names = TRIPLES[kind]
        if names[0] not in self.columns:
            return np.zeros(len(self), dtype=bool)
        return ~np.isnan(self.columns[names[0]])  # triples are all-or-none per row (validated)

    def _triple(self, kind: str, rows: np.ndarray) -> np.ndarray:
        if not rows.any():
            return _readonly(np.zeros((0, 3)))
        return _readonly(np.column_stack([self.columns[n][rows] for n in TRIPLES[kind]]))

    @cached_property
    def mag_rows(self) -> np.ndarray:
        """(N,) bool: rows carrying a magnetometer sample (all of mx,my,mz)."""
        return _readonly(self._rows("mag"))

    @cached_property
    def mag(self) -> np.ndarray:
        """(M,3) magnetometer samples in :attr:`mag_unit` (only the mag rows)."""
        return self._triple("mag", self.mag_rows)

    @cached_property
    def t_mag(self) -> np.ndarray:
        """(M,) time of each magnetometer sample, seconds."""
        return _readonly(self.t[self.mag_rows])

    @cached_property
    def accel_rows(self) -> np.ndarray:
        """(N,) bool: rows carrying an accelerometer sample."""
        return _readonly(self._rows("accel"))

    @cached_property
    def accel(self) -> np.ndarray:
        """(A,3) accelerometer samples in :attr:`accel_unit` (only the accel rows)."""
        return self._triple("accel", self.accel_rows)

    @cached_property
    def gyro_rows(self) -> np.ndarray:
        """(N,) bool: rows carrying a gyroscope sample."""
        return _readonly(self._rows("gyro"))

    @cached_property
    def gyro(self) -> np.ndarray:
        """(G,3) gyroscope samples, rad/s (only the gyro rows)."""
        return self._triple("gyro", self.gyro_rows)

    @property
    def aux_names(self) -> list[str]:
        """Auxiliary channels: every column that is not t, a sensor axis, temp or the logged
        attitude (``att_q*``), file order."""
        return [name for name in self.columns if name not in KNOWN and name not in ATTITUDE_COLUMNS]

    @property
    def mag_unit(self) -> str:
        """Unit of mx,my,mz: ``"uT"`` unless ``# mag_unit:`` names another (e.g. ``"counts"``)."""
        return _unit(self.metadata.get("mag_unit"), "uT")

    @property
    def accel_unit(self) -> str:
        """Unit of ax,ay,az: ``"m/s^2"`` unless ``# accel_unit:`` names another."""
        return _unit(self.metadata.get("accel_unit"), "m/s^2")

    def covariates_at_mag(self) -> dict[str, np.ndarray]:
        """Every non-magnetometer column at the magnetometer instants: ``{name: (M,)}``.

        ``t`` is :attr:`t_mag`. Other columns (temp, aux channels, ax..az, gx..gz) take the value
        on the mag row itself when sampled there, else linear interpolation in time between the
        rows where they are sampled; outside that span the nearest sample is held. Columns with
        no sample at all are left out.
        """
        t_mag = self.t_mag
        rows = self.mag_rows
        out = {TIME: t_mag}
        for name, values in self.columns.items():
            if name == TIME or name in MAG:
                continue
            sampled = ~np.isnan(values)
            if not sampled.any():
                continue
            at_mag = np.interp(t_mag, self.t[sampled], values[sampled])
            same_row = values[rows]
            own = ~np.isnan(same_row)
            at_mag[own] = same_row[own]
            out[name] = _readonly(at_mag)
        return out

    def blocks(self, n: int) -> Iterator:
        """Yield :class:`streamcal.samples.SampleBlock` s of ``n`` consecutive rows
        (the last may be shorter); sensors the track lacks are None, unsampled instants NaN."""
        if int(n) < 1:
            raise InputError(f"block size must be a positive number of rows, got {n}")
        n = int(n)
        mag = np.column_stack([self.columns[c] for c in MAG])
        accel = np.column_stack([self.columns[c] for c in ACCEL]) if ACCEL[0] in self.columns \
            else None
        gyro = np.column_stack([self.columns[c] for c in GYRO]) if GYRO[0] in self.columns \
            else None
        temp = self.columns.get(TEMP)
        source = self.metadata.get("source") or (str(self.path) if self.path else "")
        for start in range(0, len(self), n):
            part = slice(start, start + n)
            yield SampleBlock(
                t=self.t[part], mag=mag[part],
                accel=None if accel is None else accel[part],
                gyro=None if gyro is None else gyro[part],
                temp=None if temp is None else temp[part],
                aux={name: self.columns[name][part] for name in self.aux_names},
                source=source)


def _validate(columns: dict[str, np.ndarray]) -> None:
    """The rules a file reader enforces, for arrays: finite t non-decreasing, no inf,
    sensor triples all-or-none per row."""
    t = columns[TIME]
    if np.isnan(t).any() or np.isinf(t).any():
        row = int(np.flatnonzero(~np.isfinite(t))[0])
        raise TrackError(f"row {row}: every row needs a finite time, got {float(t[row])!r}",
                         column=TIME, row=row)
    if len(t) > 1 and (np.diff(t) < 0).any():
        row = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
        raise TrackError(f"row {row}: time goes backwards: t={float(t[row])!r} after "
                         f"t={float(t[row - 1])!r}", column=TIME, row=row)
    for name, values in columns.items():
        if np.isinf(values).any():
            row = int(np.flatnonzero(np.isinf(values))[0])
            raise TrackError(f"row {row}: infinite value", column=name, row=row)
    for kind, triple in TRIPLES.items():
        if triple[0] not in columns:
            continue
        present = np.column_stack([~np.isnan(columns[c]) for c in triple])
        partial = present.any(axis=1) & ~present.all(axis=1)
        if partial.any():
            row = int(np.flatnonzero(partial)[0])
            raise TrackError(f"row {row}: partial {kind} sample (all three axes or none)",
                             column=triple[int(np.argmin(present[row]))], row=row)
