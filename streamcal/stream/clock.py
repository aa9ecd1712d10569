"""The calibrator's monotone sample clock (board restarts set a device's clock back)."""
from __future__ import annotations

import numpy as np

from .events import Event


class MonotoneClock:
    """Sample times made monotone across board resets.

    A board's clock restarts when it resets (a USB reconnect pulls DTR, a brown-out reboots
    it): a time earlier than the one before it continues from there instead (one typical
    interval later), this and every later time shifted by the same offset, and a
    ``clock_reset`` event says by how much. Everything downstream (forgetting by onset, held
    samples since a start, the persist test) assumes time never goes back.

    Attributes:
        t_last: the latest sample time stamped (s, on this clock; NaN before the first).
        shift: seconds added to the device's sample times since its clock went back.
        dt: typical sample interval (s) of the last stamped stage.
    """

    def __init__(self):
        self.t_last = float("nan")
        self.shift = 0.0
        self.dt = 0.0

    def adopt(self, other: "MonotoneClock") -> None:
        """Continue ``other`` (a replacement calibrator taking over a buffer stamped on it)."""
        self.shift, self.t_last, self.dt = other.shift, other.t_last, other.dt

    def stamp(self, t, events: list) -> np.ndarray:
        """Device times ``t`` (n,) s, n ≥ 1, on this clock (monotone); appends a
        ``clock_reset`` :class:`Event` to ``events`` per jump back; ``t_last`` becomes the last."""
        t = np.asarray(t, dtype=float) + self.shift if self.shift else np.asarray(t, dtype=float)
        prev = np.empty_like(t)
        prev[0] = self.t_last                       # NaN before the first stage: no jump
        prev[1:] = t[:-1]
        back = t < prev
        if not back.any():
            if len(t) > 1:
                self.dt = float(t[-1] - t[0]) / (len(t) - 1)
            self.t_last = float(t[-1])
            return t
        steps = np.diff(t)
        ahead = steps[steps > 0]
        dt = float(np.median(ahead)) if len(ahead) else self.dt
        jump = np.where(back, prev - t + dt, 0.0)    # per row, the offset added from there on
        before = np.cumsum(jump) - jump                # offset of earlier jumps in this stage
        for k in np.flatnonzero(back):
            self.shift += float(jump[k])
            at = float(prev[k] + before[k])
            events.append(Event(
                "clock_reset", f"sample clock went back {prev[k] - t[k]:.3f} s after "
                f"t={at:.3f} s (the board reset or reconnected?): later sample times are "
                f"shifted by +{self.shift:.3f} s to keep time monotone",
                {"back_by": float(prev[k] - t[k]), "at": at, "shift": self.shift}, at + dt))
        t = t + before + jump
        self.t_last = float(t[-1])
        return t
