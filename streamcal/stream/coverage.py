"""Bounded sample buffer organised by equal-area cells on the sphere of field directions.

Directions are ``x = A (m − c)`` normalised, with ``(A, c)`` the current frame: ``K⁻¹, b`` of the
calibration in use, or ``I/R, centre`` of the running sphere estimate before the first one.

Cells: :class:`~streamcal.sphere_cells.SphereCells` (equal-area, O(1) lookup).

Each cell keeps at most ``slots`` samples, at least ``min_spacing_deg`` apart (ArduPilot keeps
≥ 6.3°, PX4 6.7°); a new sample that is far from all stored samples of its cell takes a free
slot or the oldest one; a sample close to exactly one stored sample refreshes it (one refresh per
cell and block), so the buffer holds the newest samples. All arrays are preallocated: memory is
fixed by configuration.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..sphere_cells import SphereCells, hint, largest_empty_cap


def not_measured(why: str) -> str:
    """``coverage not measured: <why and what to do>`` (an unframed buffer's reason)."""
    return f"coverage not measured: {why}"


def percent(fraction: float | None, width: int = 0) -> str:
    """``93%`` (the number right-aligned in ``width``), or ``not measured`` for None (an
    unframed buffer: :attr:`CoverageBuffer.measured_fraction`)."""
    return "not measured" if fraction is None else f"{100 * fraction:{width}.0f}%"


def coverage_words(fraction: float | None) -> str:
    """``coverage 93%``, or ``coverage not measured`` for None."""
    return f"coverage {percent(fraction)}"


@dataclass(frozen=True)
class CoverageReport:
    """How well the stored samples cover the sphere of directions.

    Attributes:
        fraction: occupied cells / all cells (0..1).
        n_samples: samples stored.
        n_cells: cells of the partition.
        empty_cap_deg: angular radius (degrees) of the largest cap holding no stored sample.
        empty_cap_center: (3,) unit centre of that cap, body axes of the current frame.
        hint: what to do, in plain language.
        occupied: (n_cells,) bool, the cells holding a stored sample when the figures were
            taken (for a map that agrees with them), or None.
        unframed: why the stored samples cannot be placed on the sphere of directions yet
            ("" when they can): then fraction, gap and cells are not measured (the buffer's
            frame is no sphere through them) and ``hint`` says what to do.
    """

    fraction: float
    n_samples: int
    n_cells: int
    empty_cap_deg: float
    empty_cap_center: np.ndarray = field(repr=False)
    hint: str = ""
    occupied: np.ndarray | None = field(default=None, repr=False, compare=False)
    unframed: str = ""

    @property
    def measured(self) -> bool:
        """The directions (fraction, gap, cells) mean something: the frame is a sphere model."""
        return not self.unframed

    def text(self) -> str:
        """``coverage 93% of the sphere; largest gap 12°: <hint>`` or ``coverage not measured:
        <why and what to do>``."""
        if not self.measured:
            return not_measured(self.hint)
        return (f"coverage {100 * self.fraction:.0f}% of the sphere; largest gap "
                f"{self.empty_cap_deg:.0f}°: {self.hint}")

    def to_dict(self) -> dict:
        if not self.measured:
            return {"coverage": None, "n_samples": self.n_samples, "n_cells": self.n_cells,
                    "empty_cap_deg": None, "empty_cap_center": None, "hint": self.hint}
        return {"coverage": round(self.fraction, 4), "n_samples": self.n_samples,
                "n_cells": self.n_cells, "empty_cap_deg": round(self.empty_cap_deg, 1),
                "empty_cap_center": [round(float(v), 3) for v in self.empty_cap_center],
                "hint": self.hint}


@dataclass(frozen=True)
class Snapshot:
    """Stored samples for a fit, oldest first: ``m`` (K,3) sensor unit, ``t`` (K,) s,
    ``covariates`` {name: (K,)} (NaN where absent), ``cells`` (K,) cell index."""

    m: np.ndarray
    t: np.ndarray
    covariates: dict
    cells: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def columns(self) -> dict:
        """``{"t": t, **covariates}``: the per-sample columns a check of the samples reads."""
        return {"t": self.t, **self.covariates}

    def subset(self, mask) -> "Snapshot":
        return Snapshot(self.m[mask], self.t[mask],
                        {k: v[mask] for k, v in self.covariates.items()}, self.cells[mask])

    def to_track(self):
        """The samples as a :class:`streamcal.inputs.track.Track` (for fitters that use covariates)."""
        from ..inputs.track import Track

        aux = {k: v for k, v in self.covariates.items()
               if k not in ("temp", "ax", "ay", "az", "gx", "gy", "gz")}
        temp = self.covariates.get("temp")
        accel = _stack(self.covariates, ("ax", "ay", "az"))
        gyro = _stack(self.covariates, ("gx", "gy", "gz"))
        return Track.from_arrays(self.t, mag=self.m, accel=accel, gyro=gyro,
                                 temp=temp if temp is not None and np.isfinite(temp).any() else None,
                                 aux=aux or None)


def _stack(cov, names):
    if all(n in cov for n in names) and np.isfinite(cov[names[0]]).any():
        return np.stack([cov[n] for n in names], axis=1)
    return None


class CoverageBuffer:
    """Fixed-size buffer of samples binned by direction.

    Args:
        n_cells: about how many equal-area cells (100–500 is sensible).
        slots: samples kept per cell.
        min_spacing_deg: least angle between two stored samples of a cell.
        covariates: names of per-sample covariates kept with each sample (``temp``, ``ax``…,
            aux channel names); absent ones are stored as NaN.

    Usage::

        buf = CoverageBuffer(n_cells=300)
        buf.set_frame(center=b, A=np.linalg.inv(K))
        added = buf.insert(m, t, {"temp": temp})
        buf.fraction, buf.report().hint, buf.snapshot()
    """

    def __init__(self, n_cells: int = 300, slots: int = 4, min_spacing_deg: float = 6.3,
                 covariates: tuple[str, ...] = ("temp",)):
        self.cells = SphereCells(n_cells)
        self.slots = int(slots)
        self.min_spacing_deg = float(min_spacing_deg)
        self._cos_min = float(np.cos(np.radians(min_spacing_deg)))
        # Cells about 2/3 of the spacing wide, for thinning large batches.
        self._fine = SphereCells(max(n_cells, int(4.0 * np.pi / np.radians(min_spacing_deg / 1.5) ** 2)))
        self.covariate_names = tuple(covariates)
        C, S = self.cells.n_cells, self.slots
        self._m = np.zeros((C, S, 3))
        self._d = np.zeros((C, S, 3))
        self._t = np.full((C, S), -np.inf)
        self._cov = np.full((C, S, len(self.covariate_names)), np.nan)
        self._used = np.zeros((C, S), dtype=bool)
        self._scratch_hit = np.zeros(C, dtype=bool)
        self._scratch_d = np.zeros((C, 3))
        self._n_occupied = 0
        self.center = np.zeros(3)
        self.A = np.eye(3)
        #: why the frame places no direction yet ("" when it does: a calibration, or a sphere
        #: that the stored samples fit); set by whoever frames the buffer
        self.unframed = ""

    # -- frame ----------------------------------------------------------------------------------
    def directions(self, m: np.ndarray) -> np.ndarray:
        """Unit directions (n,3) of samples ``m`` (n,3) in the current frame."""
        x = (m - self.center) @ self.A.T
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        return x / np.where(norm > 0, norm, 1.0)

    def set_frame(self, center, A) -> None:
        """Use ``x = A (m − center)`` for directions from now on and re-bin what is stored."""
        self.center = np.asarray(center, dtype=float).reshape(3).copy()
        self.A = np.asarray(A, dtype=float).reshape(3, 3).copy()
        snap = self.snapshot()
        self.clear()
        if len(snap):
            self.insert(snap.m, snap.t, snap.covariates)

    # -- contents -------------------------------------------------------------------------------
    @property
    def nbytes(self) -> int:
        """Bytes held by the preallocated arrays (fixed whatever the samples inserted)."""
        return sum(a.nbytes for a in (self._m, self._d, self._t, self._cov, self._used))

    def stored_directions(self) -> np.ndarray:
        """(n,3) unit directions of the stored samples in the current frame."""
        return self._d[self._used]

    @property
    def capacity(self) -> int:
        return self._used.size

    @property
    def n_samples(self) -> int:
        return int(self._used.sum())

    @property
    def occupied(self) -> np.ndarray:
        """(C,) bool: cells holding at least one sample."""
        return self._used.any(axis=1)

    @property
    def fraction(self) -> float:
        """Fraction of the sphere covered: occupied cells / cells."""
        return self._n_occupied / self.cells.n_cells

    def clear(self) -> None:
        self._used[:] = False
        self._t[:] = -np.inf
        self._cov[:] = np.nan
        self._n_occupied = 0

    def forget_before(self, t_cut: float) -> int:
        """Drop samples older than ``t_cut`` (s); returns how many were dropped."""
        old = self._used & (self._t < t_cut)
        self._used &= ~old
        self._t[old] = -np.inf
        self._n_occupied = int(self.occupied.sum())
        return int(old.sum())

    def insert(self, m, t, covariates=None, d=None, cell=None) -> tuple[int, int]:
        """Offer samples ``m`` (n,3), times ``t`` (n,) s, ``covariates`` {name: (n,)} or a
        covariate matrix (n,P) in the order of ``covariate_names``.

        ``d`` (n,3), ``cell`` (n,): the samples' unit directions in the current frame and their
        cells, when the caller has computed them already (then every row must be finite).

        Returns ``(stored, new_cells)``: samples that took a new slot (or the oldest slot of a
        full cell; refreshes of a nearby stored sample do not count) and cells that were empty
        before. Rows with non-finite ``m`` are ignored.
        """
        m = np.asarray(m, dtype=float).reshape(-1, 3)
        t = np.asarray(t, dtype=float).reshape(-1)
        if isinstance(covariates, np.ndarray):
            cov = covariates.reshape(len(m), len(self.covariate_names))
        else:
            cov = np.full((len(m), len(self.covariate_names)), np.nan)
            for k, name in enumerate(self.covariate_names):
                if covariates is not None and covariates.get(name) is not None:
                    cov[:, k] = covariates[name]
        if d is None:
            ok = np.isfinite(m).all(axis=1)
            if not ok.all():
                m, t, cov = m[ok], t[ok], cov[ok]
            d = self.directions(m)
            cell = None
        if not len(m):
            return 0, 0
        if len(m) > 2 * self._fine.n_cells:
            # Large batch: keep the newest sample per fine cell (cells narrower than the spacing),
            # so the rounds below cost O(fine cells), not O(batch).
            keep = _newest_per_key(np.arange(len(m)), self._fine.cell_of(d), self._fine.n_cells)
            m, t, cov, d = m[keep], t[keep], cov[keep], d[keep]
            cell = None if cell is None else cell[keep]
        if cell is None:
            cell = self.cells.cell_of(d)
        C = self.cells.n_cells
        stored = new_cells = 0
        # Samples far from every stored sample of their cell; each round stores the newest of
        # them per cell, then only the samples just stored need checking against the rest.
        cos = np.einsum("nsk,nk->ns", self._d[cell], d)
        far = ~(self._used[cell] & (cos > self._cos_min)).any(axis=1)
        done = np.zeros(len(m), dtype=bool)
        for _ in range(self.slots + 1):
            cand = np.flatnonzero(far & ~done)
            if not len(cand):
                break
            pick = _newest_per_key(cand, cell[cand], C)
            pcell = cell[pick]
            new_cells += int((~self._used[pcell].any(axis=1)).sum())
            # Slot: a free one, else the oldest (free slots have t = −inf).
            slot = np.argmin(self._t[pcell], axis=1)
            self._write(pcell, slot, m[pick], d[pick], t[pick], cov[pick])
            stored += len(pick)
            done[pick] = True
            rest = np.flatnonzero(far & ~done)
            self._scratch_hit[pcell] = True
            self._scratch_d[pcell] = d[pick]
            rc = cell[rest]
            near = self._scratch_hit[rc] & (np.einsum("nk,nk->n", self._scratch_d[rc], d[rest])
                                            > self._cos_min)
            far[rest[near]] = False
            self._scratch_hit[pcell] = False
        self._n_occupied += new_cells
        pending = np.flatnonzero(~done)
        if len(pending):
            self._refresh(pending, cell, m, d, t, cov)
        return stored, new_cells

    def _refresh(self, pending, cell, m, d, t, cov) -> int:
        pc = cell[pending]
        cos = np.einsum("nsk,nk->ns", self._d[pc], d[pending])
        close = self._used[pc] & (cos > self._cos_min)
        only_one = close.sum(axis=1) == 1
        nearest = np.argmax(close, axis=1)
        newer = t[pending] > self._t[pc, nearest]
        sel = only_one & newer
        if not sel.any():
            return 0
        # One refresh per cell and block: two refreshes could land within the spacing.
        idx = pending[sel]
        pick = _newest_per_key(idx, cell[idx], self.cells.n_cells)
        slot = nearest[sel][np.searchsorted(idx, pick)]
        self._write(cell[pick], slot, m[pick], d[pick], t[pick], cov[pick])
        return len(pick)

    def _write(self, c, s, m, d, t, cov) -> None:
        self._m[c, s] = m
        self._d[c, s] = d
        self._t[c, s] = t
        self._cov[c, s] = cov
        self._used[c, s] = True

    def stored_mag(self) -> np.ndarray:
        """(n,3) copy of the stored magnetometer samples, in no particular order (cheaper than
        :meth:`snapshot` where only the readings matter)."""
        return self._m[self._used]

    def snapshot(self) -> Snapshot:
        """Copies of the stored samples, oldest first."""
        c, s = np.nonzero(self._used)
        order = np.argsort(self._t[c, s], kind="stable")
        c, s = c[order], s[order]
        cov = {name: self._cov[c, s, k].copy() for k, name in enumerate(self.covariate_names)}
        return Snapshot(self._m[c, s].copy(), self._t[c, s].copy(), cov, c.copy())

    # -- figures --------------------------------------------------------------------------------
    @property
    def measured_fraction(self) -> float | None:
        """:attr:`fraction` when the frame places directions (:attr:`unframed` empty), else None."""
        return None if self.unframed else self.fraction

    def report(self, n_probe: int = 1000) -> CoverageReport:
        """Coverage figures: occupied fraction, the largest empty cap and a hint — or, while
        the frame places no direction (:attr:`unframed`), that they are not measured and why."""
        if self.unframed:
            return CoverageReport(float("nan"), self.n_samples, self.cells.n_cells, float("nan"),
                                  np.full(3, np.nan), self.unframed,
                                  np.zeros(self.cells.n_cells, bool), self.unframed)
        d = self._d[self._used]
        center, radius = largest_empty_cap(d, n_probe)
        return CoverageReport(self.fraction, len(d), self.cells.n_cells, radius, center,
                              hint(center, radius, self.fraction), self.occupied.copy())


def _newest_per_key(idx: np.ndarray, key: np.ndarray, n_keys: int) -> np.ndarray:
    """Of the sample indices ``idx`` (increasing = newer), the newest one per ``key`` value,
    sorted by key."""
    newest = np.full(n_keys, -1, dtype=np.intp)
    np.maximum.at(newest, key, idx)
    return newest[newest >= 0]
