"""The service loop: device source → streaming calibrator → calibration store and sample outputs.

::

    source.read() ──▶ StreamingCalibrator.ingest ──▶ events ──▶ log (stderr), hooks (serial: send
        │  (SampleBlock)        │ (fits on a worker thread)      the accepted calibration back)
        │                       └─▶ apply, disagreement ──▶ Outputs (JSON lines: stdout and/or
        │                                 UNIX socket; ``disturbed`` per sample)
        └─ SourceUnavailable ──▶ back off (0.5 s doubling to 10 s), STATUS says why, retry forever

Signals (handled between blocks; a block takes at most about one second):

- SIGTERM, SIGINT: stop reading, wait up to ``grace_s`` for the fit in flight (its result goes
  through the guard and the store as usual), abandon it after that, ``STOPPING=1``, exit 0. The
  store writes atomically, so the calibration file is valid whatever instant the stop comes.
- SIGHUP: re-read the calibration file (``RELOADING=1`` … ``READY=1``); the coverage buffer is
  kept. A missing or damaged file leaves the calibration in use unchanged
  (docs/calibration_file.md).

systemd (``Type=notify``): ``READY=1`` once the store is loaded and the outputs listen (before the
device answers: an absent sensor is a status, not a failed start), ``WATCHDOG=1`` at half of
``WATCHDOG_USEC`` from the loop itself (a hung loop gets the service restarted), ``STATUS=`` with
coverage, rms and the device state. Memory is bounded by the calibrator's buffer and the outputs'
per-client queues, never by uptime.
"""
from __future__ import annotations

import math
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

from ..stream.coverage import coverage_words
from .notify import Notifier
from .output import Outputs
from .sources import SourceUnavailable

BACKOFF_S = (0.5, 10.0)
STATUS_EVERY_S = 2.0


@dataclass
class RunStats:
    """What the loop did; ``summary()`` is the JSON-ready form printed at exit."""

    blocks: int = 0
    samples: int = 0
    events: dict = field(default_factory=dict)
    ingest_errors: int = 0
    outages: int = 0
    reloads: int = 0
    stop_reason: str = ""


class Service:
    """Run a source through a calibrator until stopped.

    Args:
        make_calibrator: ``make_calibrator(buffer=None) -> StreamingCalibrator`` (with its store);
            called at start and on reload (with the previous buffer, to keep the coverage).
        source: an adapter of :mod:`streamcal.service.sources`.
        outputs: :class:`~streamcal.service.output.Outputs` for calibrated samples.
        notifier: :class:`~streamcal.service.notify.Notifier` (default from the environment).
        max_seconds: stop after this many wall-clock seconds (None: run until a signal).
        on_calibration: ``on_calibration(cal, service)`` each time the calibration in use
            changes (loaded, accepted, recalled, re-read); returns an optional message to log
            (the serial host sends the calibration to the board here).
        log: ``log(line)``; default prints to stderr.
        on_coverage: ``on_coverage(calibrator)`` after each coverage milestone event (the CLIs
            draw :func:`streamcal.report.terminal.coverage_view` here).
        grace_s: how long a stop waits for the fit in flight.
        name: command name in log lines.
        observers: objects told what the loop does, on the loop's thread: ``on_block(service,
            block)`` after each block (None when idle or the device is absent),
            ``on_events(events)`` with the calibrator's events, ``close()`` at the end (the live
            page, :mod:`streamcal.service.live_state`). They must return quickly.
    """

    def __init__(self, make_calibrator: Callable, source, *, outputs: Outputs | None = None,
                 notifier: Notifier | None = None, max_seconds: float | None = None,
                 on_calibration: Callable | None = None, log: Callable[[str], None] | None = None,
                 on_coverage: Callable | None = None, grace_s: float = 10.0, name: str = "daemon",
                 observers=()):
        self.make_calibrator, self.source = make_calibrator, source
        self.outputs = outputs if outputs is not None else Outputs()
        self.notifier = notifier if notifier is not None else Notifier()
        self.max_seconds, self.grace_s, self.name = max_seconds, grace_s, name
        self.on_calibration = on_calibration
        self.on_coverage = on_coverage
        self.observers = list(observers)
        self.log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self.stats = RunStats()
        self.cal_version = 0
        self.calibrator = None
        self._cal_seen = None
        self.device_state = "starting"
        self._stop: str | None = None
        self._reload = False
        self._last_status = -math.inf

    # -- control (signal handlers call these; they only set flags) -------------------------------
    def request_stop(self, reason: str = "stop requested") -> None:
        self._stop = self._stop or reason

    def request_reload(self) -> None:
        self._reload = True

    def install_signal_handlers(self) -> None:
        names = {signal.SIGTERM: "SIGTERM", signal.SIGINT: "SIGINT"}
        for sig, label in names.items():
            signal.signal(sig, lambda s, f, label=label: self.request_stop(label))
        signal.signal(signal.SIGHUP, lambda s, f: self.request_reload())

    # -- the loop ---------------------------------------------------------------------------------
    def run(self) -> int:
        """Run until a signal, ``max_seconds`` or the end of a replay; returns the exit code."""
        start = time.monotonic()
        self.calibrator = self.make_calibrator()
        self._handle(self.calibrator.poll())
        self.notifier.ready(self._status_text())
        self.log(f"streamcal {self.name}: ready; source {self.source.description}")
        backoff = BACKOFF_S[0]
        try:
            while self._stop is None:
                if self.max_seconds is not None and time.monotonic() - start >= self.max_seconds:
                    self.request_stop(f"--max-seconds {self.max_seconds:g} reached")
                    break
                if self._reload:
                    self._do_reload()
                try:
                    block = self.source.read()
                except SourceUnavailable as exc:
                    if self.device_state != "absent":
                        self.stats.outages += 1
                        self.log(f"streamcal {self.name}: device not answering: {exc}")
                    self.device_state = "absent"
                    self._status(force=True, extra=f"retrying in {backoff:g} s")
                    self._observe(None)
                    self._pause(backoff)
                    backoff = min(2 * backoff, BACKOFF_S[1])
                    continue
                if self.device_state != "running":
                    if self.device_state == "absent":
                        self.log(f"streamcal {self.name}: device answers again")
                    self.device_state = "running"
                backoff = BACKOFF_S[0]
                if block is None:
                    if self.source.finished:
                        self.request_stop("end of replay")
                    self._handle(self.calibrator.poll())
                    self.outputs.publish((), (), self.cal_version)
                else:
                    self._ingest(block)
                self._observe(block)
                self.notifier.tick()
                self._status()
            self._finish()
        finally:
            self.outputs.close()
            for observer in self.observers:
                observer.close()
            self.source.close()
            self.notifier.close()
        if self._stop == "end of replay" and self.calibrator.calibration is None:
            return 1
        return 0

    def _ingest(self, block) -> None:
        self.stats.blocks += 1
        self.stats.samples += len(block)
        try:
            events = self.calibrator.ingest(block)
            self._handle(events)
            cal = self.calibrator
            self.outputs.publish(block.t, cal.apply(block), self.cal_version,
                                 cal.disagreement(block) if self.outputs else None)
        except Exception as exc:   # a bug or a hostile block must not take the service down
            self.stats.ingest_errors += 1
            if self.stats.ingest_errors <= 10 or self.stats.ingest_errors % 1000 == 0:
                self.log(f"streamcal {self.name}: block dropped ({type(exc).__name__}: {exc}); "
                         f"{self.stats.ingest_errors} so far")

    def _observe(self, block) -> None:
        for observer in self.observers:
            observer.on_block(self, block)

    def _finish(self) -> None:
        reason = self._stop or "stopped"
        self.stats.stop_reason = reason
        busy = self.calibrator.fit_in_flight
        self.notifier.stopping(f"stopping ({reason})")
        if busy:
            self.log(f"streamcal {self.name}: {reason}; waiting up to {self.grace_s:g} s for the "
                     "fit in flight")
        self._handle(self.calibrator.close(timeout=self.grace_s))
        if self.calibrator.fit_in_flight:
            self.log(f"streamcal {self.name}: fit still running after {self.grace_s:g} s; "
                     "abandoned (the calibration file is unchanged)")
        self.log(f"streamcal {self.name}: stopped ({reason}); {self._status_text()}")

    def _do_reload(self) -> None:
        self._reload = False
        self.stats.reloads += 1
        self.notifier.reloading()
        store = self.calibrator.store
        found = store.load() if store is not None else None
        if found is None or found.calibration is None:
            why = "; ".join(found.problems) if found is not None else "no state directory"
            self.log(f"streamcal {self.name}: SIGHUP: nothing to reload ({why}); the calibration "
                     "in use is kept")
        else:
            old, self.calibrator = self.calibrator, self.make_calibrator(buffer=self.calibrator.buffer)
            self.calibrator.adopt_clock(old)    # the buffer's samples carry its clock
            self._handle(self.calibrator.poll())
            self.log(f"streamcal {self.name}: SIGHUP: calibration re-read from {found.path}")
        self.notifier.ready(self._status_text())

    def _pause(self, seconds: float) -> None:
        """Wait ``seconds`` on the source's clock in short steps, watching signals and the watchdog."""
        end = time.monotonic() + seconds
        while self._stop is None and not self._reload:
            self.notifier.tick()
            left = end - time.monotonic()
            if left <= 0:
                return
            step = min(left, 0.2)
            before = time.monotonic()
            self.source.sleep(step)
            if time.monotonic() - before < 0.5 * step:   # a stepped fake does not sleep: no spin
                return

    # -- events and status ----------------------------------------------------------------------
    def _handle(self, events) -> None:
        if events:
            for observer in self.observers:
                observer.on_events(events)
        for event in events:
            kind = event.kind
            self.stats.events[kind] = self.stats.events.get(kind, 0) + 1
            when = f"{event.t:.2f} s " if event.t is not None and math.isfinite(event.t) else ""
            self.log(f"streamcal {self.name}: {when}{kind}: {event.message}")
            if kind == "coverage" and self.on_coverage is not None:
                self.on_coverage(self.calibrator)
        cal = self.calibrator.calibration
        if cal is not None and cal is not self._cal_seen:
            self._cal_seen = cal
            self.cal_version += 1
            if self.on_calibration is not None:
                extra = self.on_calibration(cal, self)
                if extra:
                    self.log(f"streamcal {self.name}: {extra}")

    def _status_text(self, extra: str = "") -> str:
        cal = self.calibrator.calibration if self.calibrator is not None else None
        cov = self.calibrator.buffer.measured_fraction if self.calibrator is not None else 0.0
        parts = [f"device {self.device_state}" + (f" ({extra})" if extra else ""),
                 coverage_words(cov)]
        if cal is not None:
            from ..units import with_unit

            rms = with_unit(f"{cal.rms:.3g}", cal.unit) if math.isfinite(cal.rms) else "n/a"
            parts.append(f"calibration v{self.cal_version} rms {rms}")
        else:
            parts.append("no calibration yet")
        parts.append(f"{self.stats.samples} samples")
        counters = self.source.counters()
        errors = counters.get("bus_errors", counters.get("lost", 0))
        parts.append(f"{errors} {'bus errors' if 'bus_errors' in counters else 'frames lost'}")
        return ", ".join(parts)

    def _status(self, force: bool = False, extra: str = "") -> None:
        now = time.monotonic()
        if force or now - self._last_status >= STATUS_EVERY_S:
            self._last_status = now
            self.notifier.status(self._status_text(extra))

    def summary(self) -> dict:
        """JSON-ready figures of the run (printed by the CLI at exit)."""
        cal = self.calibrator.calibration if self.calibrator is not None else None
        out = {"event": "summary", "stop_reason": self.stats.stop_reason,
               "blocks": self.stats.blocks, "samples": self.stats.samples,
               "events": dict(self.stats.events), "ingest_errors": self.stats.ingest_errors,
               "outages": self.stats.outages, "reloads": self.stats.reloads,
               "cal_version": self.cal_version, "output_lines": self.outputs.lines,
               "coverage": _rounded(self.calibrator.buffer.measured_fraction)
               if self.calibrator is not None else 0.0,
               "source": self.source.counters()}
        if cal is not None:
            out.update({"K": cal.K.tolist(), "b": cal.b.tolist(),
                        "rms": float(cal.rms) if math.isfinite(cal.rms) else None})
        return out


def _rounded(fraction: float | None) -> float | None:
    return None if fraction is None else round(float(fraction), 4)
