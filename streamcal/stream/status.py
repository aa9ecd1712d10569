"""The calibrator's state in words, at least every few seconds of sample time: a stream that
calibrates nothing is never silent.

Events report what happened (a fit failed, a disturbance ended…); between them a ``status``
event says what holds: ``no calibration: <reason> since t=… s`` while no calibration is in force
(or the one in use is stale), every ``every_s`` s of sample time, and ``calibration in use since
t=… s`` every ``calibrated_every_s`` s while one is. A run of failed or rejected fits is summed up
in it (how many since when, the last reason). :meth:`StatusReporter.final` gives the state when
the stream ends.
"""
from __future__ import annotations

import math

from ..units import display_unit
from .coverage import percent
from .events import Event


class StatusReporter:
    """Keeps what the ``status`` events need from the events of a calibrator.

    Args:
        every_s: sample time (s) between status events while no calibration is in force (they
            come with a stage of samples, up to 2.6 s later at 100 Hz: 7 s keeps the gaps
            within 10 s).
        calibrated_every_s: the same while a calibration is in force.
    """

    def __init__(self, every_s: float = 7.0, calibrated_every_s: float = 60.0):
        self.every_s = float(every_s)
        self.calibrated_every_s = float(calibrated_every_s)
        self.last_t = -math.inf         # last status event
        self.reason = ""                # state and key of the reason reported last
        self.since = math.nan           # when that reason began (s)
        self.in_force_since = math.nan  # the calibration in force since (s)
        self.failures = 0               # fits failed or rejected since the last acceptance
        self.failures_since = math.nan
        self.last_failure = ""

    def after(self, events: list, cal, t_now: float) -> list:
        """Note ``events`` (those of one stage) of the calibrator ``cal`` at sample time
        ``t_now`` (s); returns ``[status event]`` when one is due, else ``[]``."""
        for e in events:
            self._note(e)
        calibrated = cal.calibration is not None and not cal.stale
        every = self.calibrated_every_s if calibrated else self.every_s
        if not math.isfinite(self.last_t):  # the first samples: counted from the first one
            start = cal.environments.start
            self.last_t = start if math.isfinite(start) else t_now
        if t_now - self.last_t < every:
            return []
        return [self.event(cal, t_now)]

    def final(self, cal, t_now: float) -> Event:
        """The state when the stream ends at ``t_now`` (s)."""
        e = self.event(cal, t_now)
        return Event(e.kind, f"stream ended at t={t_now:.2f} s: {e.message}",
                     {**e.data, "final": True}, t_now)

    def event(self, cal, t_now: float) -> Event:
        """A ``status`` event for the calibrator ``cal`` at ``t_now`` (s)."""
        self.last_t = t_now
        if cal.calibration is not None and not cal.stale:
            since = self.in_force_since
            c, unit = cal.calibration, display_unit(cal.calibration.unit)
            text = ("calibration in use" + (f" since t={since:.2f} s" if math.isfinite(since)
                                               else " (loaded)")
                    + f", rms {c.rms:.3g}{' ' + unit if unit else ''}, coverage "
                    f"{percent(cal.buffer.measured_fraction)}")
            return Event("status", text, self._data("calibrated", "", since, cal), t_now)
        key, reason, hint = self._reason(cal)
        state = "stale" if cal.calibration is not None else "uncalibrated"
        if f"{state}:{key}" != self.reason or not math.isfinite(self.since):
            self.reason, self.since = f"{state}:{key}", t_now
        head = ("no calibration (the one in use is stale: the field changed)"
                if state == "stale" else "no calibration")
        failed = ""
        if self.failures:
            failed = (f"; {self.failures} fit{'s' if self.failures > 1 else ''} failed or "
                      f"rejected since t={self.failures_since:.2f} s (last: "
                      f"{self.last_failure.split('. ')[0].split(' (')[0]})")
        return Event("status", f"{head}: {reason} since t={self.since:.2f} s{failed}"
                     + (f"; {hint}" if hint else ""),
                     self._data(state, key, self.since, cal), t_now)

    # -- internals --------------------------------------------------------------------------------
    def _note(self, e: Event) -> None:
        if e.kind in ("fit_failed", "rejected"):
            if not self.failures:
                self.failures_since = e.t
            self.failures += 1
            self.last_failure = (e.message.removeprefix("fit failed: ")
                                 .removeprefix("candidate rejected: "))
        elif e.kind in ("accepted", "recalled"):
            self.failures, self.last_failure = 0, ""
            self.in_force_since = e.t
        elif e.kind == "drift":
            self.failures, self.last_failure = 0, ""

    def _reason(self, cal) -> tuple[str, str, str]:
        """``(key, reason, what to do)``: why no calibration is in force now."""
        dist = cal.tracker.open
        if dist is not None:
            return "disturbance", (f"a disturbance (the field disagrees with the reference "
                                   f"since t={dist.start:.2f} s), not judged yet"), ""
        if cal.fit_in_flight:
            return "fitting", "a fit is running", ""
        buffer, policy = cal.buffer, cal.policy
        if buffer.unframed:
            why, _, hint = buffer.unframed.partition("): ")
            return "unframed", f"coverage not measured: {why})" if hint else \
                f"coverage not measured: {buffer.unframed}", hint
        turn = "rotate the board through more orientations"
        if buffer.n_samples < policy.min_samples:
            return "few_samples", (f"too few distinct directions ({buffer.n_samples} samples "
                                   f"stored, a first fit needs {policy.min_samples})"), turn
        plateau = (f", or {percent(policy.plateau_coverage)} once no new direction came for "
                   f"{policy.plateau_s:g} s" if policy.may_plateau(cal.calibration, True) else "")
        return "coverage", (f"too little coverage ({percent(buffer.fraction)} of the sphere; a "
                            f"first fit needs {percent(policy.min_coverage)}{plateau})"), turn

    def _data(self, state: str, key: str, since: float, cal) -> dict:
        return {"state": state, "reason": key or None,
                "since": since if math.isfinite(since) else None,
                "failures": self.failures, "coverage": cal.buffer.measured_fraction}
