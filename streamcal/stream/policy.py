"""When to fit: first when coverage suffices, later when new information arrived or the field
disagrees with the calibration in use (the environment changed).

Drift statistic: over the last ``window`` magnetometer samples, the median of
``|‖K⁻¹(m − b)‖ − 1|`` (relative field error) under the calibration in use. Its limit is
``max(k · rms / radius, floor)``: for Gaussian errors the median of |e| is 0.67 σ, so with the
default ``k = 4`` a correct calibration exceeds it essentially never, while a new hard-iron
offset of a few percent of the field does at once. The window is a preallocated ring.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FitRequest:
    """Why a fit is wanted now (``reason``) with the figures that triggered it."""

    reason: str
    data: dict


class RecalPolicy:
    """Decide when to fit.

    Args:
        min_coverage: sphere fraction needed for a first fit.
        plateau_coverage, plateau_s: a first fit also starts at this lower sphere fraction once
            no new cell was filled for ``plateau_s`` s of sample time (the board keeps turning
            through the same directions): whether the directions determine the model is then
            the fit's to say (it refuses an undetermined one) and the guard's (the candidate
            must beat the reference on held-out samples). Only on a measured frame, and while
            no calibration fitted on ``min_coverage`` is in use, stale or not
            (:meth:`may_plateau`). Again after each ``plateau_s`` without new cells.
        min_samples: stored samples needed for a first fit.
        new_cells: refit after this fraction of the cells was newly filled since the last fit…
        new_samples: …or this fraction of the buffer capacity was newly stored (new slots, not
            refreshes) and ``refit_interval_s`` passed: coverage is complete, the fit only
            follows slow changes.
        min_interval_s: least sample time between fit requests (s).
        refit_interval_s: least sample time between fits triggered by new samples alone (s).
        window: samples in the drift window.
        drift_k, drift_floor: drift limit ``max(k · rms/radius, floor)`` (relative units).
    """

    def __init__(self, *, min_coverage: float = 0.35, plateau_coverage: float = 0.25,
                 plateau_s: float = 8.0, min_samples: int = 100,
                 new_cells: float = 0.05, new_samples: float = 0.25, min_interval_s: float = 2.0,
                 refit_interval_s: float = 30.0, window: int = 200, drift_k: float = 4.0,
                 drift_floor: float = 0.03):
        self.min_coverage = min_coverage
        self.plateau_coverage = plateau_coverage
        self.plateau_s = plateau_s
        self.min_samples = min_samples
        self.new_cells = new_cells
        self.new_samples = new_samples
        self.min_interval_s = min_interval_s
        self.refit_interval_s = refit_interval_s
        self.drift_k = drift_k
        self.drift_floor = drift_floor
        self._err = np.zeros(int(window))
        self._t = np.zeros(int(window))
        self.reset_counts()
        self.reset_window()
        self.last_request_t = -np.inf
        self.last_new_cell_t = -np.inf

    @property
    def window(self) -> int:
        """Samples in the drift window."""
        return len(self._err)

    @property
    def nbytes(self) -> int:
        """Bytes held by the drift window (fixed)."""
        return self._err.nbytes

    # -- new information ----------------------------------------------------------------------
    def reset_counts(self) -> None:
        self.cells_since = 0
        self.stored_since = 0

    def note(self, stored: int, new_cells: int, t: float = -np.inf) -> None:
        """Count what the buffer gained from the last block (ending at sample time ``t`` s)."""
        self.stored_since += int(stored)
        self.cells_since += int(new_cells)
        if new_cells:
            self.last_new_cell_t = max(self.last_new_cell_t, float(t))

    def plateaued(self, coverage: float, t_now: float) -> bool:
        """The coverage stays between :attr:`plateau_coverage` and :attr:`min_coverage`: no new
        cell for :attr:`plateau_s` s before ``t_now``, none since the last request either."""
        quiet = min(t_now - self.last_new_cell_t, t_now - self.last_request_t)
        return self.plateau_coverage <= coverage < self.min_coverage and quiet >= self.plateau_s

    def may_plateau(self, in_use, measured: bool) -> bool:
        """The plateau rule may start a fit: the coverage is ``measured`` (about a sphere the
        samples fit) and the calibration ``in_use`` (stale or not; None) was not fitted on
        :attr:`min_coverage`. A stale calibration of a well-covered sphere stays until a fit of
        the same coverage replaces it, or it is recalled when its field returns; one fitted on
        a plateau is no better than a new plateau fit."""
        if not measured:
            return False
        cov = None if in_use is None else in_use.coverage
        return in_use is None or cov is not None and cov < self.min_coverage

    def want_fit(self, *, calibrated: bool, coverage: float, n_samples: int, n_cells: int,
                 capacity: int, t_now: float, plateau: bool = False) -> FitRequest | None:
        """A :class:`FitRequest` when a fit should start now, else None; ``plateau``: the
        plateau rule may serve (:meth:`may_plateau`)."""
        if t_now - self.last_request_t < self.min_interval_s or n_samples < self.min_samples:
            return None
        if not calibrated and plateau and self.plateaued(coverage, t_now):
            reason = "coverage_plateau"
        elif coverage < self.min_coverage:
            return None
        elif not calibrated and self.last_request_t == -np.inf:
            reason = "coverage_reached"
        elif self.cells_since >= max(1, self.new_cells * n_cells):
            reason = "new_cells"
        elif (self.stored_since >= max(1, self.new_samples * capacity)
                and t_now - self.last_request_t >= self.refit_interval_s):
            reason = "new_samples"
        else:
            return None
        return FitRequest(reason, {"coverage": round(coverage, 4), "n_samples": n_samples,
                                   "new_cells": self.cells_since,
                                   "new_samples": self.stored_since})

    def requested(self, t_now: float) -> None:
        self.last_request_t = t_now
        self.reset_counts()

    def restart(self) -> None:
        """Forget the fit history (after the environment changed): the next fit is a first one."""
        self.last_request_t = -np.inf
        self.last_new_cell_t = -np.inf
        self.reset_counts()
        self.reset_window()

    # -- drift --------------------------------------------------------------------------------
    def reset_window(self) -> None:
        self._n = 0
        self._checked_at = 0

    def observe(self, rel_err: np.ndarray, t: np.ndarray) -> None:
        """Push relative errors ``|‖x‖ − 1|`` (n,) at times ``t`` (n,) s into the window."""
        W = len(self._err)
        rel_err, t = rel_err[-W:], t[-W:]
        k = len(rel_err)
        start = self._n % W
        first = min(k, W - start)                # up to the end of the ring, then from 0
        self._err[start:start + first] = rel_err[:first]
        self._t[start:start + first] = t[:first]
        self._err[:k - first] = rel_err[first:]
        self._t[:k - first] = t[first:]
        self._n += k

    def drift_limit(self, rms: float, radius: float) -> float:
        rel = rms / radius if np.isfinite(rms) and radius > 0 else 0.0
        return max(self.drift_k * rel, self.drift_floor)

    def check(self, rms: float, radius: float) -> WindowCheck | None:
        """Judge a full window, and then once per quarter window of new samples; None when no
        judgement is due."""
        W = len(self._err)
        if self._n < W or self._n - self._checked_at < W // 4:
            return None
        self._checked_at = self._n
        limit = self.drift_limit(rms, radius)
        beyond = self._err > limit
        onset = float(self._t[beyond].min()) if beyond.any() else float("nan")
        return WindowCheck(_median(self._err), limit, float(beyond.mean()), onset)


@dataclass(frozen=True)
class WindowCheck:
    """One judgement of the drift window: ``stat`` its median relative error, ``limit`` the drift
    limit, ``fraction`` of its samples beyond the limit, ``onset`` the time (s) of the earliest
    of them (NaN when none). The window disagrees when ``stat > limit``."""

    stat: float
    limit: float
    fraction: float
    onset: float

    @property
    def disagrees(self) -> bool:
        return self.stat > self.limit


def _median(x: np.ndarray) -> float:
    """Median of ``x`` (n,) by partial sorting (np.median's overhead dominates for n ~ 200)."""
    n = len(x)
    part = np.partition(x, [(n - 1) // 2, n // 2])
    return float(0.5 * (part[(n - 1) // 2] + part[n // 2]))
