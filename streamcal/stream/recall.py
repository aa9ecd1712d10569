"""Recall of remembered calibrations after an environment change.

The last ``remember`` accepted calibrations are remembered with the cells they were fitted on.
While the calibration in use is stale, a window of the newest samples is kept; a full window
(then every quarter window) is checked against each remembered calibration (K, b only), newest
first, and one that fits it within its drift limit over ``checks`` consecutive checks is
recalled: the magnet was removed, the board is back in its old place.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration


@dataclass(frozen=True)
class Recall:
    """A remembered calibration that fits again: ``stat`` the window's median relative error
    ≤ ``limit``, over samples since ``start`` (s); ``support`` the cells it was fitted on."""

    calibration: Calibration
    support: np.ndarray | None
    stat: float
    limit: float
    start: float


class Recaller:
    """Remembered calibrations and the window of new samples checked against them.

    Args:
        window: samples per check window.
        remember: calibrations remembered (the oldest is forgotten first).
        checks: consecutive checks a calibration must pass.
        drift_limit: ``drift_limit(rms, radius) -> float``, the relative error limit of a
            calibration (the policy's).
    """

    def __init__(self, window: int, remember: int, checks: int, drift_limit):
        self._m = np.empty((int(window), 3))
        self._t = np.empty(int(window))
        self._n = 0
        self._at = 0
        self._streak: tuple = (None, 0)
        self._remembered: deque = deque(maxlen=max(1, int(remember)))
        self.checks = max(1, int(checks))
        self._drift_limit = drift_limit

    @property
    def remembered(self) -> tuple:
        """``(calibration, support)`` pairs remembered, oldest first."""
        return tuple(self._remembered)

    @property
    def capacity(self) -> int:
        """Calibrations remembered at most."""
        return self._remembered.maxlen

    @property
    def nbytes(self) -> int:
        """Bytes held by the window (fixed)."""
        return self._m.nbytes + self._t.nbytes

    def remember(self, cal: Calibration, support: np.ndarray | None) -> None:
        """Remember ``cal`` fitted on the cells ``support`` (C,) bool (None: all)."""
        self._remembered.append((cal, support))

    def restart(self) -> None:
        """Watch the new field from here on (an empty window, no streak)."""
        self._n = self._at = 0
        self._streak = (None, 0)

    def observe(self, m, t) -> Recall | None:
        """Add samples ``m`` (n,3) sensor unit at ``t`` (n,) s; a :class:`Recall` when a
        remembered calibration has fitted the window over ``checks`` consecutive checks."""
        W = len(self._t)
        m, t = m[-W:], t[-W:]
        k = len(m)
        pos = (self._n + np.arange(k)) % W
        self._m[pos] = m
        self._t[pos] = t
        self._n += k
        if self._n < W or self._n - self._at < W // 4:
            return None
        self._at = self._n
        for cal, support in reversed(self._remembered):
            if cal.effects:
                continue
            x = np.linalg.solve(cal.K, (self._m - cal.b).T).T
            stat = float(np.median(np.abs(np.linalg.norm(x, axis=1) - 1.0)))
            limit = self._drift_limit(cal.rms, cal.radius)
            if stat <= limit:
                break
        else:
            self._streak = (None, 0)
            return None
        # The same calibration must fit over consecutive checks (a window and then
        # ``checks − 1`` quarter windows): a new environment's field can cross the old sphere
        # for a moment.
        streak = self._streak[1] + 1 if self._streak[0] is cal else 1
        self._streak = (cal, streak)
        if streak < self.checks:
            return None
        self._streak = (None, 0)
        return Recall(cal, support, stat, limit, float(self._t.min()))
