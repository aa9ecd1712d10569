"""Feed the live page (:class:`~streamcal.service.live_state.LiveState` observers) from a loop
that is not a :class:`~streamcal.service.Service`: ``streamcal replay --realtime --http``.

The observers read what a service offers (``calibrator``, ``stats.samples``, ``stats.events``,
``cal_version``, ``device_state``, ``source.counters()``); :class:`ReplayFeed` keeps those for
a bare calibrator loop, which calls :meth:`ReplayFeed.observe` once per block with the events
that block caused.
"""
from __future__ import annotations

from .daemon import RunStats


class _NoCounters:
    def counters(self) -> dict:
        return {}


class ReplayFeed:
    """A service-shaped view of ``calibrator`` for ``observers`` (each with ``on_block(service,
    block)``, ``on_events(events)`` and ``close()``)."""

    def __init__(self, calibrator, observers):
        self.calibrator = calibrator
        self.observers = list(observers)
        self.stats = RunStats()
        self.cal_version = 0
        self.device_state = "replaying"
        self.source = _NoCounters()
        self._cal_seen = None

    def observe(self, block, events) -> None:
        """After ``calibrator.ingest(block)`` returned ``events``."""
        self.stats.blocks += 1
        self.stats.samples += len(block)
        for e in events:
            self.stats.events[e.kind] = self.stats.events.get(e.kind, 0) + 1
        cal = self.calibrator.calibration
        if cal is not None and cal is not self._cal_seen:
            self._cal_seen, self.cal_version = cal, self.cal_version + 1
        for o in self.observers:
            if events:
                o.on_events(events)
            o.on_block(self, block)

    def close(self, finished: bool = False) -> None:
        """``finished``: the whole recording was replayed (``stats.stop_reason`` says so, as a
        service's does at the end of a replay)."""
        self.device_state = "ended"
        if finished:
            self.stats.stop_reason = "end of replay"
        for o in self.observers:
            o.close()
