"""Staging of incoming rows: the cheap front of :meth:`StreamingCalibrator.ingest`.

A call to ``ingest`` with one sample must cost a few microseconds, while the per-block work
(binning, running sums, drift statistic) costs a fixed ~100 µs plus a little per sample. So rows
are copied, unvalidated, into preallocated arrays (``capacity`` rows) and handed on together when
the stage is full: the fixed cost is paid once per ``capacity`` rows, and nothing is allocated per
call. Validation (rows without a magnetometer sample are dropped) and sample-and-hold of the
covariates happen once per stage, vectorized.

Covariates are read from a :class:`~streamcal.samples.SampleBlock` by name: ``temp``, the
IMU axes ``ax ay az gx gy gz`` and auxiliary channels; a covariate the block lacks is NaN, and a
covariate missing on a magnetometer row takes the last value seen (sensors run at different
rates). The held values carry over from one stage to the next.
"""
from __future__ import annotations

import numpy as np

_IMU = {"ax": ("accel", 0), "ay": ("accel", 1), "az": ("accel", 2),
        "gx": ("gyro", 0), "gy": ("gyro", 1), "gz": ("gyro", 2)}


def covariate_source(block, name: str):
    """The (n,) column of covariate ``name`` in ``block``, or None when the block lacks it."""
    if name == "temp":
        return block.temp
    if name in _IMU:
        group, axis = _IMU[name]
        arr = getattr(block, group)
        return None if arr is None else np.asarray(arr)[:, axis]
    return block.aux.get(name)


def block_covariates(block) -> dict:
    """Every covariate of ``block`` by name, plus ``t`` ({name: (n,)}), for ``Calibration.apply``."""
    cov = {"t": np.asarray(block.t, dtype=float)}
    if block.temp is not None:
        cov["temp"] = np.asarray(block.temp, dtype=float)
    for name, (group, axis) in _IMU.items():
        arr = getattr(block, group)
        if arr is not None:
            cov[name] = np.asarray(arr, dtype=float)[:, axis]
    cov.update({k: np.asarray(v, dtype=float) for k, v in block.aux.items()})
    return cov


class Stage:
    """Preallocated rows waiting to be processed, and the held covariate values.

    Args:
        capacity: rows staged before :attr:`full` (≥ 1).
        covariates: covariate names, in the order of the columns of the covariate matrix.

    Usage::

        stage = Stage(256, ("temp",))
        if stage.push(block):             # True when the stage is full
            m, t, cov = stage.take()      # valid magnetometer rows, covariates held
    """

    def __init__(self, capacity: int, covariates: tuple[str, ...]):
        self.capacity = max(1, int(capacity))
        self.names = tuple(covariates)
        self.m = np.empty((self.capacity, 3))
        self.t = np.empty(self.capacity)
        self.cov = np.full((self.capacity, len(self.names)), np.nan)
        self.held = np.full(len(self.names), np.nan)
        self.n = 0

    def room(self) -> int:
        return self.capacity - self.n

    def push(self, block, n: int) -> bool:
        """Copy the ``n`` rows of ``block`` (``n ≤ room()``); True when the stage is now full."""
        k, end = self.n, self.n + n
        self.t[k:end] = block.t
        self.m[k:end] = block.mag
        if self.names:
            for j, name in enumerate(self.names):
                src = covariate_source(block, name)
                if src is not None:
                    self.cov[k:end, j] = src
        self.n = end
        return end == self.capacity

    def n_valid(self) -> int:
        """Staged rows that carry a magnetometer sample."""
        return int(np.isfinite(self.m[:self.n]).all(axis=1).sum())

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The staged rows with a magnetometer sample: ``m`` (k,3), ``t`` (k,) s, covariates
        (k,P) held; the stage is emptied. The arrays are fresh copies."""
        k, self.n = self.n, 0
        m, t = self.m[:k], self.t[:k]
        ok = np.isfinite(m).all(axis=1)
        if self.names:
            cov = self.hold(self.cov[:k])[ok]
            self.cov[:k] = np.nan
        else:
            cov = np.empty((int(ok.sum()), 0))
        return m[ok], t[ok], cov

    def take_with(self, block) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`take` followed by :meth:`rows_of` ``block``, in one set of arrays (the staged
        rows first: taking them fills their missing covariates from what came before, and
        ``rows_of`` then carries the covariates forward from them)."""
        staged = self.take() if self.n else None
        m, t, cov = self.rows_of(block)
        if staged is None:
            return m, t, cov
        m0, t0, cov0 = staged
        return np.concatenate([m0, m]), np.concatenate([t0, t]), np.concatenate([cov0, cov])

    def rows_of(self, block) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like :meth:`take` for a whole ``block`` that bypasses the stage (large blocks)."""
        m = np.asarray(block.mag, dtype=float)
        t = np.asarray(block.t, dtype=float)
        ok = np.isfinite(m).all(axis=1)
        if not self.names:
            return m[ok], t[ok], np.empty((int(ok.sum()), 0))
        raw = np.full((len(t), len(self.names)), np.nan)
        for j, name in enumerate(self.names):
            src = covariate_source(block, name)
            if src is not None:
                raw[:, j] = src
        return m[ok], t[ok], self.hold(raw)[ok]

    def hold(self, raw: np.ndarray) -> np.ndarray:
        """Sample and hold (n,P): a NaN takes the last finite value above it in its column, or
        the value held from earlier stages; updates the held values."""
        seen = np.isfinite(raw)
        if not seen.any():
            return np.broadcast_to(self.held, raw.shape)
        idx = np.where(seen, np.arange(len(raw))[:, None], -1)
        np.maximum.accumulate(idx, axis=0, out=idx)
        cols = np.arange(raw.shape[1])
        out = np.where(idx >= 0, raw[np.maximum(idx, 0), cols], self.held)
        if len(raw):
            last = idx[-1]
            self.held = np.where(last >= 0, raw[np.maximum(last, 0), cols], self.held)
        return out
