"""Other CSV/TSV files: map their columns onto track columns and convert the magnetometer unit.

    --columns mx=MagX,my=MagY,mz=MagZ,t=time_s,temp=T   --unit mG

Keys are track column names (``t``, ``mx..mz``, ``ax..az``, ``gx..gz``, ``temp`` or any valid
auxiliary name); values are header names in the file. The delimiter is a tab if the header has
one, else ``;`` if it has no comma, else ``,``. Lines starting with ``#`` before the header are
skipped. Empty cells are "not sampled" (NaN). Without a ``t`` mapping, ``t`` is the row number
(said in the metadata). ``--unit`` converts mx,my,mz to µT; ``counts`` keeps them and declares
``mag_unit: counts``.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import InputError, TrackError
from .track import Track
from .trackio import ACCEL, COLUMN_NAME, GYRO, MAG, TEMP, TIME

#: µT per unit of the magnetometer columns; ``counts`` is kept as is.
UT_PER_UNIT = {"uT": 1.0, "nT": 1e-3, "mG": 0.1, "G": 100.0, "counts": None}
_UNIT_ALIASES = {"ut": "uT", "µt": "uT", "μt": "uT", "nt": "nT", "mg": "mG", "g": "G",
                 "gauss": "G", "milligauss": "mG", "count": "counts", "counts": "counts",
                 "lsb": "counts"}


def parse_columns(spec: str | Mapping[str, str] | None) -> dict[str, str] | None:
    """``"mx=MagX,my=MagY"`` → ``{"mx": "MagX", "my": "MagY"}`` (validated)."""
    if spec is None:
        return None
    if isinstance(spec, Mapping):
        pairs = dict(spec)
    else:
        pairs = {}
        for item in str(spec).split(","):
            if not item.strip():
                continue
            key, eq, name = item.partition("=")
            if not eq or not key.strip() or not name.strip():
                raise InputError(f"--columns: expected KEY=NAME, got {item.strip()!r}")
            if key.strip() in pairs:
                raise InputError(f"--columns: {key.strip()} is mapped twice "
                                 f"({key.strip()}={pairs[key.strip()]}, {item.strip()})")
            pairs[key.strip()] = name.strip()
    twice = {name for name in pairs.values() if list(pairs.values()).count(name) > 1}
    if twice:
        name = sorted(twice)[0]
        keys = ", ".join(f"{k}={v}" for k, v in pairs.items() if v == name)
        raise InputError(f"--columns: the file's column {name!r} is mapped twice ({keys}); "
                         "one file column cannot be two track columns")
    for key in pairs:
        if not COLUMN_NAME.fullmatch(key):
            raise InputError(f"--columns: {key!r} is not a valid track column name")
    missing = [k for k in MAG if k not in pairs]
    if missing:
        raise InputError(f"--columns must map {', '.join(missing)} (the magnetometer axes)")
    return pairs


def parse_unit(unit: str | None) -> str:
    """Canonical unit name (``uT``, ``nT``, ``mG``, ``G``, ``counts``); None means ``uT``."""
    if unit is None:
        return "uT"
    canonical = _UNIT_ALIASES.get(str(unit).strip().lower())
    if canonical is None:
        raise InputError(f"--unit: expected one of {', '.join(UT_PER_UNIT)}, got {unit!r}")
    return canonical


def _delimiter(header: str) -> str:
    if "\t" in header:
        return "\t"
    if "," not in header and ";" in header:
        return ";"
    return ","


def _to_float(cells: list[str], path, lines: np.ndarray, name: str, skip: np.ndarray) -> np.ndarray:
    stripped = np.char.strip(np.array(cells, dtype=str))
    empty = stripped == ""
    out = np.full(len(cells), np.nan)
    try:
        out[~empty] = stripped[~empty].astype(np.float64)
        bad = ~np.isfinite(out) & ~empty
    except ValueError:
        bad = np.zeros(len(cells), dtype=bool)
        for k in np.flatnonzero(~empty):
            try:
                out[k] = float(stripped[k])
            except ValueError:
                bad[k] = True
        bad |= ~np.isfinite(out) & ~empty
    if bad.any() and skip is None:
        k = int(np.flatnonzero(bad)[0])
        raise TrackError(f"not a finite number: {cells[k]!r}", str(path), int(lines[k]), name)
    if skip is not None:
        skip |= bad
    out[bad] = np.nan
    return out


def read_columns_file(path, text: str, columns: Mapping[str, str], unit: str | None = None, *,
                      skip_bad_rows: bool = False) -> Track:
    """Track from a delimited text file whose columns are named by ``columns``."""
    unit = parse_unit(unit)
    raw_lines = text.replace("\r\n", "\n").split("\n")
    index = next((i for i, line in enumerate(raw_lines)
                  if line.strip() and not line.lstrip().startswith("#")), None)
    if index is None:
        raise TrackError("no header row", str(path))
    delim = _delimiter(raw_lines[index])
    header = [c.strip().strip('"') for c in raw_lines[index].split(delim)]
    where = {name: k for k, name in enumerate(header)}
    absent = [f"{key}={name}" for key, name in columns.items() if name not in where]
    if absent:
        raise TrackError(f"--columns names columns the header does not have: {', '.join(absent)} "
                         f"(header: {', '.join(header)})", str(path), index + 1)
    body = [(i + 1, line) for i, line in enumerate(raw_lines[index + 1:], start=index + 1)
            if line.strip() and not line.lstrip().startswith("#")]
    if not body:
        raise TrackError("no data rows after the header", str(path), index + 1)
    lines = np.array([n for n, _ in body])
    rows = [re.split(re.escape(delim), line) for _, line in body]
    short = np.array([len(r) < len(header) for r in rows])
    if short.any() and not skip_bad_rows:
        k = int(np.flatnonzero(short)[0])
        raise TrackError(f"{len(rows[k])} cells, the header has {len(header)}", str(path),
                         int(lines[k]))
    skip = short.copy() if skip_bad_rows else None
    values = {}
    for key, name in columns.items():
        j = where[name]
        cells = [r[j] if j < len(r) else "" for r in rows]
        values[key] = _to_float(cells, path, lines, name, skip)
    keep = ~skip if skip is not None else np.ones(len(rows), dtype=bool)
    values = {k: v[keep] for k, v in values.items()}
    meta = {"source": f"{Path(path).name} (columns {','.join(f'{k}={v}' for k, v in columns.items())})",
            "input_format": "csv-columns"}
    if TIME in values:
        t = values.pop(TIME)
    else:
        t = np.arange(int(keep.sum()), dtype=np.float64)
        meta["time"] = "no t column mapped: t is the row number (not seconds)"
    mag = np.column_stack([values.pop(k) for k in MAG])
    factor = UT_PER_UNIT[unit]
    if factor is None:
        meta["mag_unit"] = "counts"
    else:
        mag = mag * factor
        meta["mag_unit"] = "uT"
        meta["mag_converted"] = f"from {unit} (x{factor:g})"

    def triple(names):
        return np.column_stack([values.pop(k) for k in names]) if names[0] in values else None

    accel, gyro = triple(ACCEL), triple(GYRO)
    temp = values.pop(TEMP, None)
    try:
        track = Track.from_arrays(t, mag=mag, accel=accel, gyro=gyro, temp=temp, aux=values,
                                  metadata=meta)
    except TrackError as exc:     # located by array row: say the file's line and the mapping
        if exc.row is None or exc.column not in columns:
            raise
        what = exc.reason.split(": ", 1)[-1]
        raise TrackError(f"{what} (--columns {exc.column}={columns[exc.column]})", str(path),
                         int(lines[keep][exc.row]), exc.column) from None
    track.skipped_rows = int((~keep).sum())
    return track
