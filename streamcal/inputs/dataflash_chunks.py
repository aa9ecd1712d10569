"""An ArduPilot DataFlash log read as consecutive time-ordered Tracks, memory bounded by the piece
read, not the log.

:func:`iter_dataflash_chunks` gives Tracks whose rows, put end to end, are exactly the Track of
:func:`streamcal.inputs.dataflash.read_dataflash` (same columns, values, order and metadata); each
carries the whole log's metadata. The file is read twice, :data:`PIECE_BYTES` at a time, through
the resumable header walk (:class:`.dataflash_bulk.Walker`):

1. a survey: the small message types (everything but ``MAG*`` and ``IMU``, ~10 Hz) are kept whole
   and made into their streams by the whole-log reader's own functions; of the compasses and the
   IMU only what the whole-log decisions need is kept (row counts, finite rows, the earliest time
   of each piece, the distinct squared magnitudes of the logged field with their counts for its
   median, the distinct offsets);
2. the compass and IMU rows, piece by piece, through the same row arithmetic
   (:func:`.dataflash_mag.mag_values`); a row is given out once no later piece holds an earlier stamp
   (from the survey), so the merge order is the whole log's stable time sort.

What is held grows with the small message types only (and with the compass samples when their
fields are not integers: the magnitudes for the median), not with the size of the log. A log whose message formats change
part-way, or that the whole-log reader would refuse, is read whole (same Track, same error),
then given out in slices; a log of one piece is read whole, once.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError
from .autopilot_cal import MG_PER_UT, ardupilot_param_index
from .dataflash import (MAG_NAMES, MESSAGES, _Messages, _time, add_params, compass_meta,
                        head_meta, read_dataflash, slow_streams, walk_notes)
from .dataflash_bulk import Walker, decode
from .dataflash_mag import mag_meta, mag_values
from .streams import Stream, drop_nonfinite, merge
from .track import Track

#: Bytes of the log read at a time.
PIECE_BYTES = 4 << 20
#: Rows per Track given out when a log is read whole (the fallback).
SLICE_ROWS = 100_000
HEAVY = ("MAG", "MAG2", "MAG3", "IMU")
_IMU = ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ")
_MAGC = ("MagX", "MagY", "MagZ")


class _Fallback(Exception):
    """The log is read whole instead."""


@dataclass
class _Rows:
    """Survey of one compass's or the IMU's rows: ``count`` rows, ``finite`` of them without a
    non-finite value, ``piece_min[k]`` the earliest finite stamp in piece k (s)."""

    count: int = 0
    finite: int = 0
    piece_min: dict = field(default_factory=dict)
    norms: "_NormMedian" = field(default_factory=lambda: _NormMedian())
    ofs: list = field(default_factory=list)
    mofs_nonzero: bool = False
    temp_nonzero: bool = False
    total: int = 0           # IMU: rows of every instance


class _NormMedian:
    """The median of the logged field's magnitude ``|MagX, MagY, MagZ|`` over the log, as
    ``np.median(np.linalg.norm(logged, axis=1))`` gives it. Integer fields (every ArduPilot
    layout) are held as the distinct squared magnitudes and their counts (exact integers: a
    few thousand values for hours of log), others as every magnitude."""

    def __init__(self):
        self.squares = np.zeros(0, np.int64)
        self.counts = np.zeros(0, np.int64)
        self.floats: list = []

    def add(self, logged: np.ndarray, chars: str) -> None:
        if all(c in "bBhHM" for c in chars):   # |value| ≤ 65535: squares sum exactly
            sq = np.sum(logged.astype(np.int64) ** 2, axis=1)
            values, inverse = np.unique(np.concatenate([self.squares, sq]), return_inverse=True)
            counts = np.bincount(inverse[len(self.squares):], minlength=len(values))
            counts[inverse[:len(self.squares)]] += self.counts
            self.squares, self.counts = values, counts
        else:
            self.floats.append(np.linalg.norm(logged, axis=1))

    def median(self) -> float:
        if self.floats or not len(self.squares):
            norms = np.sqrt(np.repeat(self.squares, self.counts).astype(np.float64))
            return float(np.median(np.concatenate([norms, *self.floats])))
        n = int(self.counts.sum())
        cum = np.cumsum(self.counts)
        middle = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
        values = np.sqrt(self.squares[np.searchsorted(cum, middle, side="right")]
                         .astype(np.float64))
        return float(np.mean(values))


def _pieces(path: Path, walker: Walker, piece_bytes: int) -> Iterator[tuple]:
    """``(data, base, {type: offsets in data})`` of consecutive stretches of the file (``base``
    the file offset of ``data``)."""
    try:
        handle = open(path, "rb")
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    with handle:
        carry, base = b"", 0
        while True:
            block = handle.read(piece_bytes)
            data = carry + block
            offsets, kinds, resume = walker.feed(data, base, final=not block)
            by_type = {t: offsets[kinds == t] for t in np.unique(kinds).tolist()}
            yield data, base, by_type
            if not block:
                return
            carry, base = data[resume:], base + resume


def _decode(data, by_type, chain, names, used: dict) -> dict:
    """``{name: (Format, columns)}`` of the wanted message types present in this stretch
    (``chain`` the walk's formats and name map)."""
    out = {}
    for name in names:
        ftype = chain.name_to_type.get(name)
        if ftype is None or ftype not in by_type:
            continue
        fmt = chain.formats[ftype]
        used.setdefault(name, set()).add((ftype, fmt.name, fmt.length, fmt.format,
                                          tuple(fmt.columns)))
        try:
            out[name] = (fmt, decode(data, fmt, by_type[ftype]))
        except ValueError:
            raise _Fallback from None
    return out


def _finite(t, *arrays) -> np.ndarray:
    ok = np.isfinite(t)
    for a in arrays:
        ok &= np.all(np.isfinite(a), axis=1) if a.ndim == 2 else np.isfinite(a)
    return ok


def _survey_heavy(msgs: _Messages, path, piece: int, rows: dict) -> None:
    """Add this piece's compass and IMU rows to ``rows``: key ``(name, I)`` per compass message
    name and instance field value (``I`` None when the message has no such field), ``"IMU"``
    for the IMU's instance 0."""
    def add(key, t, *values):
        r = rows.setdefault(key, _Rows())
        ok = _finite(t, *values)
        r.count += len(t)
        r.finite += int(ok.sum())
        if ok.any():
            r.piece_min[piece] = float(t[ok].min())
        return r

    for name in MAG_NAMES:
        if not msgs.count(name):
            continue
        if not msgs.has(name, *_MAGC):   # the whole-log reader refuses this compass
            rows.setdefault((name, "no MagX/Y/Z"), _Rows()).count += msgs.count(name)
            continue
        ids = msgs.array(name, "I") if msgs.has(name, "I") else None
        t_all = _time(msgs, name, path)   # once per message name, sliced per instance
        for inst in (np.unique(ids).tolist() if ids is not None else [None]):
            sel = (ids == inst) if ids is not None else slice(None)
            t = t_all[sel]
            logged = np.column_stack([msgs.array(name, c)[sel] for c in _MAGC])
            mofs = np.column_stack([msgs.array(name, c)[sel] for c in ("MOfsX", "MOfsY", "MOfsZ")]
                                   ) if msgs.has(name, "MOfsX", "MOfsY", "MOfsZ") else None
            ofs = np.column_stack([msgs.array(name, c)[sel] for c in ("OfsX", "OfsY", "OfsZ")]
                                  ) if msgs.has(name, "OfsX", "OfsY", "OfsZ") else None
            r = add((name, None if inst is None else int(inst)), t, logged,
                    *[a for a in (mofs, ofs) if a is not None])
            r.norms.add(logged, "".join(msgs.types[name][c] for c in _MAGC))
            r.mofs_nonzero |= mofs is not None and bool(np.any(mofs))
            if ofs is not None:
                r.ofs.append(np.unique(ofs, axis=0))
    if msgs.count("IMU") and msgs.has("IMU", *_IMU):
        sel = (msgs.array("IMU", "I") == 0) if msgs.has("IMU", "I") else slice(None)
        t = _time(msgs, "IMU", path)[sel]
        values = [msgs.array("IMU", c)[sel] for c in _IMU]
        temp = [msgs.array("IMU", "Temp")[sel]] if msgs.has("IMU", "Temp") else []
        r = add("IMU", t, *values, *temp)
        r.temp_nonzero |= bool(temp and np.any(temp[0] != 0))
        r.total += msgs.count("IMU")


@dataclass
class _Plan:
    """What the survey decided: the whole log's metadata, ``t0`` (s since boot), the track's
    columns, the small streams (whole, non-finite rows dropped), the compass (message name,
    instance, parameter index) and the IMU (None: no IMU stream; else whether it has temp),
    ``bound[k]`` the earliest stamp of any compass/IMU row after piece k, and the walk's
    formats (``chain``)."""

    meta: dict
    t0: float
    names: list
    small: list
    mag: tuple
    imu: bool | None
    bound: np.ndarray
    fields: dict
    types: dict
    params: dict
    chain: object = None


def _survey(path: Path, compass: int | None, piece_bytes: int) -> _Plan:
    walker = Walker()
    used: dict = {}
    small = {name: [] for name in MESSAGES if name not in HEAVY + ("PARM", "MSG")}
    formats: dict = {}
    params, texts, rows = {}, [], {}
    n_pieces = 0
    for k, (data, _, by_type) in enumerate(_pieces(path, walker, piece_bytes)):
        n_pieces = k + 1
        decoded = _decode(data, by_type, walker.walk, MESSAGES, used)
        piece = _Messages(path=path, params=params)
        for name, (fmt, cols) in decoded.items():
            if name == "PARM" and {"Name", "Value"} <= set(cols):
                add_params(params, cols, path)
            elif name == "MSG" and "Message" in cols:
                texts += [str(m) for m in cols["Message"].tolist()]
            elif name not in ("PARM", "MSG"):
                formats[name] = fmt
                if name in small:
                    small[name].append(cols)
                else:
                    piece.fields[name] = list(fmt.columns)
                    piece.types[name] = dict(zip(fmt.columns, fmt.format))
                    piece.cols[name] = cols
        _survey_heavy(piece, path, k, rows)
    final = walker.walk
    for name, seen in used.items():   # formats must not change part-way
        ftype = final.name_to_type.get(name)
        fmt = final.formats.get(ftype)
        if fmt is None or seen != {(ftype, fmt.name, fmt.length, fmt.format,
                                    tuple(fmt.columns))}:
            raise _Fallback
    msgs = _Messages(path=path, params=params, texts=texts)
    for name, fmt in formats.items():
        msgs.fields[name] = list(fmt.columns)
        msgs.types[name] = dict(zip(fmt.columns, fmt.format))
        if name in small:
            msgs.cols[name] = {c: np.concatenate([p[c] for p in small[name]])
                               for c in small[name][0]}
    msgs.texts += walk_notes(final)
    plan = _plan(msgs, rows, path, compass, n_pieces)
    plan.chain = final
    return plan


def _mag_keys(rows: dict) -> list:
    return [(k, r) for k, r in rows.items() if k != "IMU"]


def _plan(msgs: _Messages, rows: dict, path: Path, compass, n_pieces: int) -> _Plan:
    """The decisions of :func:`streamcal.inputs.dataflash._track`, from the survey."""
    layout_i = "MAG" in msgs.fields and "I" in msgs.fields["MAG"]
    if layout_i:
        present = sorted(i for (n, i), r in _mag_keys(rows)
                         if n == "MAG" and isinstance(i, int) and r.count)
    else:
        present = [i for i, n in enumerate(MAG_NAMES)
                   if any(r.count for (m, _), r in _mag_keys(rows) if m == n)]
    primary = int(msgs.params.get("COMPASS_PRIMARY", 0) or 0)
    instance = compass if compass is not None else (primary if primary in present else 0)
    if instance not in present:
        raise _Fallback   # the whole-log reader names what is missing
    name = "MAG" if layout_i else MAG_NAMES[instance]
    key = (name, instance if name in msgs.fields and "I" in msgs.fields[name] else None)
    if key not in rows:
        raise _Fallback   # no MagX/Y/Z, or no rows of that instance: the reader says so
    mag_rows = rows[key]
    meta = head_meta(msgs, path, instance, present)
    params_of = ardupilot_param_index(msgs.params, instance)
    meta["compass_params_index"] = str(params_of)
    meta["autopilot_field_uT"] = f"{mag_rows.norms.median() / MG_PER_UT:.4g}"
    heads = _Messages(dict(msgs.fields), dict(msgs.types), {}, msgs.params, msgs.texts, path)
    heads.cols[name] = {}   # has() looks at the fields only
    mag_meta(heads, name, params_of, meta, mag_rows.mofs_nonzero,
             np.unique(np.concatenate(mag_rows.ofs), axis=0) if mag_rows.ofs else None)
    counts = [(name, mag_rows)]
    imu = None
    imu_rows = rows.get("IMU")
    if imu_rows is not None and imu_rows.total:
        imu = bool(imu_rows.temp_nonzero)
        if imu:
            meta["temp_source"] = "IMU.Temp (the IMU's die temperature)"
        counts.append(("IMU", imu_rows))
    small = slow_streams(msgs, path, meta, baro=not imu)
    compass_meta(msgs, params_of, meta)
    # drop_nonfinite of the whole log: the compass/IMU counts from the survey, in stream order
    kept = drop_nonfinite(small, scratch := {})
    dropped = [f"{r.count - r.finite} {n}" for n, r in counts if r.count > r.finite]
    if scratch.get("read_warnings"):
        dropped.append(scratch["read_warnings"].split(": ", 1)[1])
    if dropped:
        note = "dropped rows with non-finite values (damaged bytes): " + ", ".join(dropped)
        meta["read_warnings"] = "; ".join(filter(None, (meta.get("read_warnings"), note)))
    if not mag_rows.finite:
        raise _Fallback
    firsts = [min(r.piece_min.values()) for _, r in counts if r.finite] + \
        [float(s.t.min()) for s in kept if len(s.t)]
    t0 = min(firsts)
    meta["time_origin"] = f"log time {t0:.6f} s since boot is t = 0"
    meta["log_t0_s"] = f"{t0:.6f}"
    meta["messages"] = ", ".join([f"{n} {r.finite}" for n, r in counts] +
                                 [f"{s.name} {len(s.t)}" for s in kept])
    streams_cols = [("mx", "my", "mz")] if mag_rows.finite else []
    if imu is not None and imu_rows.finite:
        streams_cols.append(("ax", "ay", "az", "gx", "gy", "gz") + (("temp",) if imu else ()))
    streams_cols += [tuple(s.columns) for s in kept if len(s.t)]
    names = list(dict.fromkeys(c for cols in streams_cols for c in cols))
    # bound[k]: earliest compass/IMU stamp in pieces after k
    mins = np.full(n_pieces + 1, np.inf)
    for _, r in counts:
        for k, v in r.piece_min.items():
            mins[k] = min(mins[k], v)
    bound = np.minimum.accumulate(mins[::-1])[::-1][1:]
    return _Plan(meta, t0, names, kept, (name, instance, params_of), imu,
                 bound, msgs.fields, msgs.types, msgs.params)


def _heavy_streams(plan: _Plan, decoded: dict, path: Path) -> list[Stream]:
    """This piece's compass and IMU streams (non-finite rows dropped)."""
    msgs = _Messages(plan.fields, plan.types, {}, plan.params, [], path)
    for n, (_, cols) in decoded.items():
        if n in HEAVY:
            msgs.cols[n] = cols
    out = []
    name, inst, params_of = plan.mag
    if msgs.count(name):
        m = msgs
        if msgs.has(name, "I"):
            keep = msgs.array(name, "I") == inst
            m = _Messages(msgs.fields, msgs.types, {name: {c: v[keep] for c, v in
                                                           msgs.cols[name].items()}},
                          msgs.params, [], path)
        out.append(Stream(name, _time(m, name, path),
                          mag_values(m, name, params_of,
                                     order=plan.meta["ardupilot_correction_order"])))
    if plan.imu is not None and msgs.count("IMU"):
        m = msgs
        if msgs.has("IMU", "I"):
            keep = msgs.array("IMU", "I") == 0
            m = _Messages(msgs.fields, msgs.types, {"IMU": {c: v[keep] for c, v in
                                                            msgs.cols["IMU"].items()}},
                          msgs.params, [], path)
        cols = dict(zip(("ax", "ay", "az", "gx", "gy", "gz"), (m.array("IMU", c) for c in _IMU)))
        if plan.imu:
            cols["temp"] = m.array("IMU", "Temp")
        out.append(Stream("IMU", _time(m, "IMU", path), cols))
    return drop_nonfinite(out, {})


def _take(pending: list, limit: float) -> tuple[list, list]:
    """Split each pending stream into rows before ``limit`` and the rest."""
    now, rest = [], []
    for s in pending:
        early = s.t < limit
        if early.all():
            now.append(s)
            continue
        now.append(Stream(s.name, s.t[early], {k: v[early] for k, v in s.columns.items()}))
        rest.append(Stream(s.name, s.t[~early], {k: v[~early] for k, v in s.columns.items()}))
    return now, rest


def iter_dataflash_chunks(path, *, compass: int | None = None,
                          piece_bytes: int | None = None) -> Iterator[Track]:
    """Yield the DataFlash log at ``path`` (compass ``compass``, default the autopilot's first)
    as consecutive Tracks in time order whose rows end to end are
    :func:`~streamcal.inputs.dataflash.read_dataflash`'s Track; InputError as that function."""
    path = Path(path)
    piece_bytes = int(piece_bytes or PIECE_BYTES)
    try:
        small = path.stat().st_size <= piece_bytes
    except OSError:
        small = True    # the whole-log reader names the problem
    if small:   # one piece: read once, not twice
        yield _whole(path, compass)
        return
    try:
        plan = _survey(path, compass, piece_bytes)
    except (_Fallback, InputError):
        yield from _slices(_whole(path, compass))
        return
    order = ["MAG", "IMU"]   # stream order of the whole-log reader: compass, IMU, then small
    pending_small = list(plan.small)
    pending_heavy: list = []
    # the same walk again gives the same pieces (their message offsets are not kept)
    for k, (data, _, by_type) in enumerate(_pieces(path, Walker(), piece_bytes)):
        decoded = _decode(data, by_type, plan.chain, HEAVY, {})
        heavy = _heavy_streams(plan, decoded, path)
        pending_heavy += heavy
        limit = plan.bound[k] if k < len(plan.bound) else np.inf
        now_h, pending_heavy = _take(pending_heavy, limit)
        now_s, pending_small = _take(pending_small, limit)
        chunk = _emit(plan, now_h, now_s, order, path)
        if chunk is not None:
            yield chunk
    chunk = _emit(plan, pending_heavy, pending_small, order, path)
    if chunk is not None:
        yield chunk


def _emit(plan: _Plan, heavy: list, small: list, order, path) -> Track | None:
    """The rows of ``heavy`` (pieces of the compass and IMU streams) and ``small`` merged in the
    whole-log reader's stream order."""
    streams = []
    for kind in order:
        parts = [s for s in heavy if (s.name == "IMU") == (kind == "IMU")]
        if parts:
            streams.append(Stream(parts[0].name, np.concatenate([s.t for s in parts]),
                                  {c: np.concatenate([s.columns[c] for s in parts])
                                   for c in parts[0].columns}))
    streams += small
    if not any(len(s.t) for s in streams):
        return None
    track = merge(streams, plan.meta, t0=plan.t0, names=plan.names)
    track.path = path
    return track


def _whole(path: Path, compass) -> Track:
    track = read_dataflash(path, compass=compass)
    track.path = path
    return track


def _slices(track: Track, rows: int = SLICE_ROWS) -> Iterator[Track]:
    """A whole Track given out as Tracks of at most ``rows`` rows (views, metadata shared)."""
    for a in range(0, max(len(track), 1), rows):
        yield track.select(slice(a, a + rows))
