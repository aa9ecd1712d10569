"""Diagnosis of long recordings from a stratified subsample read on the fly (issue #13 item 2).

A long track is never held whole. :class:`StratifiedSampler` reads it chunk by chunk and keeps
short contiguous *blocks* of rows (:data:`BLOCK_S` seconds: magnetometer rows and the IMU rows
between them, so interpolated covariates, gyro pairs and noise second-differences stay valid
inside a block; the fits drop pairs across gaps). Two strata decide which blocks stay:

- **time**: the span is cut into between :data:`TIME_BINS` and 2·:data:`TIME_BINS` equal bins
  (the bin width doubles, merging neighbours, as the recording grows — its length need not be
  known); each bin keeps :data:`PER_BIN` blocks spread round-robin over the sphere cells it
  visits, the lowest random priority first in each cell. Every part of the time span keeps its
  samples, so drift, temperature and motor channels keep their leverage.
- **direction**: every equal-area sphere cell (:class:`streamcal.sphere_cells.SphereCells`, the
  coverage buffer's partition, :data:`N_CELLS` cells) the recording visits keeps its
  lowest-priority block, so no visited direction is lost. Cells are of the block's mean field
  direction about the centre of the algebraic ellipsoid fit of every sample read so far (running
  sufficient statistics).

The gravity reference of the gravity-tied residual (:mod:`streamcal.fitting.gravity`) low-passes
the accelerometer over tens of seconds: built on the subsample it would run across the gaps
between the kept blocks (a gravity-tied rms of ≈ 25 µT where the recording gives 1 µT). So it
is built on each chunk read (contiguous rows, after the last :data:`TAIL_S` seconds of the chunk
before, so the filter has settled where the chunk starts) and kept for the kept blocks' IMU
rows; a block within ``TAIL_S / 2`` of a chunk's end waits for the next chunk's reference, which
holds it well inside. Its own error (``tilt``, for the tied residual's floor) is measured on the
same chunks (:meth:`StratifiedSampler.gravity`).

Priorities are uniform random numbers from a fixed seed, so a subsample is reproducible. The
diagnosis then runs on the subsample; the outlier spans are computed over the whole recording
from a compact copy of every magnetometer sample (time float64, field and covariates float32:
20 bytes per magnetometer sample plus 4 per covariate, IMU columns left out).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Iterable, Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL
from ..fitting.ellipsoid import design_matrix
from ..errors import InsufficientDataError
from ..inputs.track import Track
from ..sphere_cells import SphereCells
from .entry import diagnose as _diagnose
from .residuals import sensor_residual
from ..fitting.outlier_rule import outlier_mask, outlier_spans

#: Length of one kept block of consecutive rows, s.
BLOCK_S = 0.2
#: The time span is cut into between TIME_BINS and 2·TIME_BINS bins.
TIME_BINS = 32
#: Blocks kept per time bin (round-robin over its sphere cells).
PER_BIN = 10
#: Equal-area sphere cells for the direction stratum.
N_CELLS = 100
#: Recordings with more magnetometer samples than this are diagnosed from a subsample (10 min
#: at 100 Hz); up to it every sample is used. Decided by the samples, whatever the format.
LONG_SAMPLES = 60_000
#: Seconds of the previous chunk the gravity reference of a chunk starts with (the zero-phase
#: 0.05 Hz low-pass settles within about 10 s).
TAIL_S = 30.0
#: Rows per chunk read from the file.
CHUNK_ROWS = 100_000
#: Samples per piece when the whole-recording residual is evaluated.
PIECE = 50_000


def _round_robin(cell: np.ndarray, u: np.ndarray, q: int) -> np.ndarray:
    """Indices of the ``q`` blocks a round-robin over cells picks (lowest ``u`` first in each
    cell, cells in order of their next-lowest ``u``): water-filling the cells to one level."""
    if len(u) <= q:
        return np.arange(len(u))
    order = np.lexsort((u, cell))
    c = cell[order]
    start = np.r_[0, np.flatnonzero(np.diff(c)) + 1]
    rank = np.arange(len(c)) - np.repeat(start, np.diff(np.r_[start, len(c)]))
    pick = np.lexsort((u[order], rank))[:q]
    return order[pick]


class StratifiedSampler:
    """Feed :meth:`add` consecutive chunks (Tracks, time order); :meth:`track` gives the
    subsample, :meth:`recording` the compact copy of every magnetometer sample."""

    def __init__(self, block_s: float = BLOCK_S, time_bins: int = TIME_BINS,
                 per_bin: int = PER_BIN, n_cells: int = N_CELLS, seed: int = 0):
        self.block_s, self.time_bins, self.per_bin = float(block_s), int(time_bins), int(per_bin)
        self.cells = SphereCells(n_cells)
        self.rng = np.random.default_rng(seed)
        self.width = 4.0 * self.block_s          # time-bin width, s (doubles as needed)
        self.t0 = None
        self.names = None
        self.metadata, self.path = {}, None
        self.scatter = np.zeros((10, 10))        # Σ DᵀD of the algebraic ellipsoid fit
        self.left = None                         # rows of the last, unfinished block
        # kept blocks: id → rows (R, C); their meta arrays
        self.rows: dict[int, np.ndarray] = {}
        self.meta = np.zeros((0, 4))             # (block id, time bin, cell, priority)
        self.best = np.zeros((0, 3))             # per visited cell: (cell, priority, block id)
        self.store = {"t": [], "mag": [], "cov": []}
        self.cov_names = None
        self.samples_total = 0
        # gravity reference: of the chunks the unfinished rows may come from, of the kept
        # blocks, and (IMU samples, tilt σ) per chunk
        self._refs: list = []
        self._tail = None                        # the last TAIL_S s of the previous chunk
        self._edge = np.inf                      # blocks ending after this wait (s)
        self._pending: set[int] = set()
        self.gref: dict[int, object] = {}
        self._tilts: list[tuple[int, float, str]] = []

    # -- reading ---------------------------------------------------------------------------
    def add(self, chunk: Track) -> None:
        """Take one chunk of the recording (a :class:`Track`)."""
        if self.names is None:
            self.names = list(chunk.columns)
            self.metadata, self.path = dict(chunk.metadata), chunk.path
        if not len(chunk):
            return
        self._keep_mag(chunk)
        self._reference(chunk)
        data = np.column_stack([chunk.columns[n] for n in self.names])
        if self.left is not None:
            data = np.concatenate([self.left, data])
        t = data[:, self.names.index("t")]
        if self.t0 is None:
            self.t0 = float(t[0])
        block = np.floor((t - self.t0) / self.block_s).astype(np.int64)
        last = block[-1]
        self.left = data[block == last]
        self._blocks(data[block < last], block[block < last])

    def _keep_mag(self, chunk: Track) -> None:
        m = np.asarray(chunk.mag, float)
        self.samples_total += len(m)
        if not len(m):
            return
        cov = chunk.covariates_at_mag()
        names = sorted(k for k in cov if k != "t" and k not in ("ax", "ay", "az", "gx", "gy", "gz"))
        if self.cov_names is None:
            self.cov_names = names
        self.store["t"].append(np.asarray(cov["t"], float))
        self.store["mag"].append(m.astype(np.float32))
        self.store["cov"].append(np.column_stack(
            [cov[k] if k in cov else np.full(len(m), np.nan) for k in self.cov_names]
        ).astype(np.float32) if self.cov_names else np.zeros((len(m), 0), np.float32))
        D = design_matrix(m)
        self.scatter += D.T @ D

    def _reference(self, chunk: Track) -> None:
        """The gravity reference of one chunk (contiguous rows, after the previous chunk's
        tail) and its error; the blocks that waited for it take theirs."""
        from ..fitting.gravity import gravity_reference, tilt_sigma

        if not chunk.has("accel") or int(np.sum(chunk.accel_rows)) < 2:
            return
        piece = chunk if self._tail is None else _concatenate([self._tail, chunk])
        self._refs = [*self._refs[-1:], gravity_reference(piece)]
        sigma, how = tilt_sigma(chunk)
        self._tilts.append((int(np.sum(chunk.accel_rows)), sigma, how))
        t = np.asarray(chunk.t, float)
        self._tail = chunk.select(t >= t[-1] - TAIL_S)
        self._edge = float(t[-1]) - TAIL_S / 2
        self._settle()

    def _settle(self) -> None:
        """The blocks waiting for a reference take the latest one."""
        for bid in self._pending:
            if bid in self.rows:
                self.gref[bid] = self._reference_rows(self.rows[bid])
        self._pending = set()

    def _reference_rows(self, rows: np.ndarray):
        """The reference at the IMU rows of a kept block's ``rows`` (R, C), from the chunk that
        holds each row; None when the track has no accelerometer."""
        from ..fitting.gravity import GravityReference

        if not self._refs:
            return None
        acols = [self.names.index(k) for k in ("ax", "ay", "az")]
        t = rows[:, self.names.index("t")][np.isfinite(rows[:, acols]).all(axis=1)]
        down, trust, taken = np.zeros((len(t), 3)), np.ones(len(t)), np.zeros(len(t), bool)
        for ref in reversed(self._refs):   # the latest holds a row furthest from its ends
            inside = ~taken & (t >= ref.t[0]) & (t <= ref.t[-1])
            if inside.any():
                down[inside], trust[inside] = ref.at(t[inside])
                taken |= inside
        return GravityReference(t[taken], down[taken], trust[taken], self._refs[-1].method)

    def gravity(self):
        """The gravity reference of the subsample (:meth:`track`): each kept block's, from the
        chunk its rows were read in, with the chunks' error (``tilt``, the rms over their IMU
        samples); None without an accelerometer."""
        from ..fitting.gravity import joined

        pieces = [self.gref[k] for k in sorted(self.gref)
                  if k in self.rows and self.gref[k] is not None]
        if not pieces or not self._tilts:
            return None
        n = np.array([k for k, _, _ in self._tilts], float)
        tilt = np.array([s for _, s, _ in self._tilts], float)
        ref = joined(pieces)
        return dataclasses.replace(ref, tilt=float(np.sqrt(np.sum(n * tilt ** 2) / n.sum())),
                                   tilt_method=self._tilts[-1][2] + ", on each chunk read")

    def _centre(self, m: np.ndarray) -> np.ndarray:
        """Centre of the algebraic ellipsoid fit of every sample so far (bounding-box middle of
        ``m`` when that fit is not an ellipsoid)."""
        w, v = np.linalg.eigh(self.scatter)
        x = v[:, 0]
        A = np.array([[x[0], x[3], x[4]], [x[3], x[1], x[5]], [x[4], x[5], x[2]]])
        if np.all(np.linalg.eigvalsh(A * np.sign(np.trace(A))) > 0):
            return -np.linalg.solve(A, x[6:9])
        return 0.5 * (np.nanmin(m, 0) + np.nanmax(m, 0))

    def _blocks(self, data: np.ndarray, block: np.ndarray) -> None:
        if not len(data):
            return
        mcols = [self.names.index(k) for k in ("mx", "my", "mz")]
        m = data[:, mcols]
        has = ~np.isnan(m).any(axis=1)
        ids, start = np.unique(block, return_index=True)
        bounds = np.r_[start, len(block)]
        sums = np.add.reduceat(np.where(has[:, None], m, 0.0), start)
        counts = np.add.reduceat(has.astype(int), start)
        ok = counts > 0                          # blocks without a magnetometer row are dropped
        mean = sums[ok] / counts[ok, None]
        d = mean - self._centre(m[has])
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        cell = self.cells.cell_of(d)
        tb = np.floor(ids[ok] * self.block_s / self.width).astype(np.int64)
        u = self.rng.random(int(ok.sum()))
        new = np.column_stack([ids[ok], tb, cell, u])
        self.meta = self._select(np.concatenate([self.meta, new]))
        self.best = self._best(np.column_stack([cell, u, ids[ok]]))
        keep = set(self.meta[:, 0].astype(np.int64)) | set(self.best[:, 2].astype(np.int64))
        for j, bid in enumerate(ids):
            if ok[j] and bid in keep and bid not in self.rows:
                self.rows[int(bid)] = rows = data[bounds[j]:bounds[j + 1]].copy()
                if rows[-1, self.names.index("t")] > self._edge:
                    self._pending.add(int(bid))    # near the chunk's end: the next one's
                else:
                    self.gref[int(bid)] = self._reference_rows(rows)
        for bid in list(self.rows):
            if bid not in keep:
                del self.rows[bid]
                self.gref.pop(bid, None)

    def _best(self, new: np.ndarray) -> np.ndarray:
        allb = np.concatenate([self.best, new])
        order = np.lexsort((allb[:, 1], allb[:, 0]))
        allb = allb[order]
        first = np.r_[True, np.diff(allb[:, 0]) != 0]
        return allb[first]

    def _select(self, meta: np.ndarray) -> np.ndarray:
        """Each time bin's round-robin pick; the bins merge pairwise while there are more than
        2·time_bins."""
        while meta[:, 1].max() - meta[:, 1].min() + 1 > 2 * self.time_bins:
            self.width *= 2.0
            meta[:, 1] = np.floor(meta[:, 0] * self.block_s / self.width)
        out = []
        for b in np.unique(meta[:, 1]):
            sel = meta[meta[:, 1] == b]
            out.append(sel[_round_robin(sel[:, 2].astype(int), sel[:, 3], self.per_bin)])
        return np.concatenate(out) if out else meta[:0]

    def finish(self) -> None:
        """Take the last, unfinished block."""
        if self.left is not None and len(self.left):
            t = self.left[:, self.names.index("t")]
            self._blocks(self.left, np.floor((t - self.t0) / self.block_s).astype(np.int64))
        self.left = None
        self._settle()   # the recording's own end: as the whole recording's reference has it

    # -- results ---------------------------------------------------------------------------
    def track(self) -> Track:
        """The kept blocks, in time order, as one Track."""
        data = np.concatenate([self.rows[k] for k in sorted(self.rows)])
        return Track({n: np.ascontiguousarray(data[:, j]) for j, n in enumerate(self.names)},
                     self.metadata, self.path)

    def recording(self):
        """The compact copy of every magnetometer sample, one piece per chunk read: yields
        ``(t (n,), mag (n,3) float32, cov {name: (n,) float32})``."""
        for t, m, c in zip(self.store["t"], self.store["mag"], self.store["cov"]):
            yield t, m, {k: c[:, j] for j, k in enumerate(self.cov_names or [])}

    def rule(self) -> str:
        return (f"stratified subsample: blocks of {self.block_s:g} s of consecutive rows; "
                f"{self.per_bin} blocks per time bin of {self.width:g} s (round-robin over "
                f"{self.cells.counts.sum()} equal-area sphere cells of the field direction, about "
                f"the running algebraic ellipsoid centre) plus one block in every visited cell; "
                f"random priorities, seed fixed")


def _whole_spans(cal, floor: float, pieces):
    """Outlier spans of calibration ``cal`` over every magnetometer sample (the one rule,
    :func:`streamcal.fitting.outlier_rule.outlier_mask`), evaluated piece by piece (``pieces`` from
    :meth:`StratifiedSampler.recording`; at most :data:`PIECE` samples at a time)."""
    ts, norms = [], []
    for t_all, m_all, cov_all in pieces:
        for a in range(0, len(t_all), PIECE):
            piece = {k: np.asarray(v[a:a + PIECE], float) for k, v in cov_all.items()}
            piece["t"] = t_all[a:a + PIECE]
            r = sensor_residual(cal, np.asarray(m_all[a:a + PIECE], float), piece)[0]
            norms.append(np.linalg.norm(r, axis=1).astype(np.float32))
        ts.append(t_all)
    t, norm = np.concatenate(ts), np.concatenate(norms)
    out = outlier_mask(norm, (getattr(cal, "extra", None) or {}).get("tau"), t, floor)
    return outlier_spans(t, out), int(out.sum())


def diagnose_chunks(chunks: Iterable[Track], model: Sequence[str] = DEFAULT_MODEL, *,
                    diagnose=_diagnose, sampler: StratifiedSampler | None = None,
                    whole_spans: bool = True, **kwargs):
    """Diagnose a recording given as consecutive chunks (e.g.
    :func:`streamcal.inputs.chunks.iter_track_chunks`) from a :class:`StratifiedSampler`
    subsample; ``diagnose(track, model, **kwargs)`` is the diagnosis to run on it
    (:func:`streamcal.diagnosis.diagnose`). The result carries ``sampling``: ``samples_used``,
    ``samples_total`` (magnetometer samples), ``subsample_rule`` and ``outlier_spans_over``
    (``"recording"`` when the spans were recomputed over every sample with the spans model,
    ``"subsample"`` otherwise); ``subsample`` is the Track used and ``gravity`` its gravity
    reference (None without an accelerometer)."""
    sampler = sampler or StratifiedSampler()
    for chunk in chunks:
        sampler.add(chunk)
    sampler.finish()
    sub = sampler.track()
    gravity = sampler.gravity()
    if gravity is not None:
        kwargs = {**kwargs, "gravity": gravity}   # the fresh diagnosis's tied fits use it
    d = diagnose(sub, model, **kwargs)
    sampling = {"samples_used": int(len(sub.mag)), "samples_total": int(sampler.samples_total),
                "subsample_rule": sampler.rule(), "outlier_spans_over": "subsample"}
    spans_cal = _spans_calibration(d)
    spans = d.outlier_spans
    if whole_spans and spans_cal is not None:
        spans, n_out = _whole_spans(spans_cal, float(d.noise_floor), sampler.recording())
        sampling.update(outlier_spans_over="recording", n_outliers_recording=n_out)
    return d.replace(outlier_spans=spans, sampling=sampling, subsample=sub, gravity=gravity)


def _spans_calibration(d):
    """The calibration of the model the spans come from (``outliers_model``), or None."""
    want = tuple(d.outliers_model or d.model)
    if tuple(d.model) == want:
        return d.calibration
    for c in d.candidates:
        cal = getattr(c, "calibration", None)
        if cal is not None and tuple(cal.model) == want:
            return cal
    return None


def _concatenate(chunks: list[Track]) -> Track:
    """Consecutive chunks of one recording as one Track (the first chunk's metadata)."""
    if len(chunks) == 1:
        return chunks[0]
    names = list(chunks[0].columns)
    return Track({n: np.concatenate([c.columns[n] for c in chunks]) for n in names},
                 chunks[0].metadata, chunks[0].path)


def diagnose_recording(chunks: Iterable[Track], model: Sequence[str] = DEFAULT_MODEL, *,
                       long_samples: int = LONG_SAMPLES, calibration_of=None,
                       diagnose=_diagnose, **kwargs):
    """``(diagnosis, track diagnosed)`` of a recording given as consecutive chunks: every
    sample when it has at most ``long_samples`` magnetometer samples, else the stratified
    subsample of :func:`diagnose_chunks` (its ``sampling`` says so). At most
    ``long_samples`` samples' rows are held before the choice is made, so the memory is
    bounded for any length and any format.

    ``calibration_of(first chunk) -> (calibration, source)``: the calibration to diagnose
    against (e.g. the autopilot's, from the log's parameters); ``kwargs`` go to ``diagnose``
    (:func:`streamcal.diagnosis.diagnose`). When the data cannot support a diagnosis, the
    :class:`~streamcal.errors.InsufficientDataError` carries the recording read as ``track``."""
    import itertools

    held, n = [], 0
    chunks = iter(chunks)
    for chunk in chunks:
        if not held and calibration_of is not None:
            cal, source = calibration_of(chunk)
            kwargs.update(calibration=cal, calibration_source=source)
        held.append(chunk)
        n += len(chunk.t_mag)
        if n > long_samples:
            d = diagnose_chunks(itertools.chain(held, chunks), model, diagnose=diagnose,
                                **kwargs)
            return d, d.subsample
    if not held:
        from ..errors import InputError

        raise InputError("the recording holds no samples")
    track = _concatenate(held)
    try:
        return diagnose(track, model, **kwargs), track
    except InsufficientDataError as exc:
        exc.track = track   # what was read, for what can still be said without a diagnosis
        raise


def diagnose_file(path: str | os.PathLike, model: Sequence[str] = DEFAULT_MODEL, *, diagnose=_diagnose,
                  rows: int = CHUNK_ROWS, skip_bad_rows: bool = False, **kwargs):
    """:func:`diagnose_chunks` of the section-1 track file at ``path``, read in chunks."""
    from ..inputs.chunks import iter_track_chunks

    return diagnose_chunks(iter_track_chunks(path, rows=rows, skip_bad_rows=skip_bad_rows),
                           model, diagnose=diagnose, **kwargs)
