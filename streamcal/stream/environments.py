"""The environments a stream went through (between environment changes), bounded."""
from __future__ import annotations

import math
from collections import deque


class EnvironmentLog:
    """The last ``keep`` environments closed, and the current one: start and end (s), the sphere
    coverage its samples reached, how many are stored, whether it was calibrated."""

    def __init__(self, keep: int = 16):
        self._closed: deque = deque(maxlen=int(keep))
        self.start = float("nan")
        self.calibrated = False

    def begin(self, t: float) -> None:
        """The first samples arrive at ``t`` (s) (only the first call counts)."""
        if math.isnan(self.start):
            self.start = float(t)

    def close(self, end: float, coverage: float | None, n_samples: int) -> None:
        """The current environment ends at ``end`` (s) with ``coverage`` (sphere fraction; None:
        not measured) and
        ``n_samples`` stored; the next begins then, not calibrated."""
        self._closed.append(self._entry(end, coverage, n_samples, self.calibrated))
        self.start, self.calibrated = end, False

    def summary(self, coverage: float, n_samples: int, calibrated: bool) -> list:
        """The environments, oldest first, the current one last (``end`` None); ``calibrated``:
        a calibration is in force now."""
        return [*self._closed,
                self._entry(None, coverage, n_samples, self.calibrated or calibrated)]

    def _entry(self, end, coverage, n_samples, calibrated) -> dict:
        start = self.start if math.isfinite(self.start) else None
        return {"start": start, "end": end,
                "coverage": None if coverage is None else round(coverage, 4),
                "n_samples": n_samples, "calibrated": calibrated}
