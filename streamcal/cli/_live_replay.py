"""A replayed device (``daemon --bus fake:…``, ``serial --port fake:…|simavr:…``) behind a live
page: watchable at the recorded pace, and the page kept up after the end.

Without ``--http`` a replay runs as fast as it can be read and the process ends with it (tests,
scripts). With ``--http`` a person is watching: a ``fake:`` replay follows the recorded pace
unless ``--speed`` says otherwise (simavr runs its own simulated clock, as fast as the host
reads), and once the track is over the page stays up, showing the final state, until a signal
or ``--max-seconds``. One line on stderr says which.
"""
from __future__ import annotations

import os
import signal
import sys
import time

from ..service.sources import FAKE_PREFIX

SIMAVR_PREFIX = "simavr:"


class TrackSpan:
    """A ``(path) -> Track`` reader that remembers the track's name and span (s)."""

    def __init__(self, read):
        self._read = read
        self.name = ""
        self.seconds: float | None = None

    def __call__(self, path):
        track = self._read(path)
        self.name = os.path.basename(str(path))
        t = getattr(track, "t", None)
        if t is not None and len(t):
            self.seconds = float(t[-1] - t[0])
        return track


def replay_speed(args, spec: str) -> float | None:
    """The pace of a replayed device: ``--speed`` when given; 1 (the recorded pace) for a
    ``fake:`` replay with ``--http``; else None (as fast as read). ``--speed`` on another device
    is an :class:`~streamcal.errors.InputError`."""
    if args.speed is not None:
        if not spec.startswith(FAKE_PREFIX):
            from ..errors import InputError

            why = ("; simavr runs as fast as the host reads" if spec.startswith(SIMAVR_PREFIX)
                   else "")
            raise InputError(f"--speed applies to a fake:TRACK.csv device only, not {spec!r}{why}")
        return args.speed
    if getattr(args, "http", None) and spec.startswith(FAKE_PREFIX):
        return 1.0
    return None


def announce(args, name: str, spec: str, speed: float | None, span: TrackSpan) -> None:
    """The one stderr line saying how a watched replay runs (nothing without ``--http`` or for
    a real device)."""
    if not getattr(args, "http", None) or not spec.startswith((FAKE_PREFIX, SIMAVR_PREFIX)):
        return
    stop = "Ctrl-C to stop" + (f" (or --max-seconds {args.max_seconds:g})"
                               if args.max_seconds is not None else "")
    if speed is None:
        how = (f"{span.name}: simavr runs as fast as the host reads (it has no recorded pace)"
               if spec.startswith(SIMAVR_PREFIX) else f"{span.name} as fast as it can be read")
    else:
        pace = "the recorded pace" if speed == 1 else f"{speed:g}× the recorded pace"
        length = "" if span.seconds is None else f" ({span.seconds / speed:.0f} s)"
        how = f"{span.name} at {pace}{length}; --speed N to change"
    print(f"streamcal {name}: replaying {how}; the page stays up after the end; {stop}",
          file=sys.stderr, flush=True)


def serve_after_replay(service, name: str, max_seconds: float | None, started: float) -> None:
    """After ``service.run()``: keep a live page up with the final state until SIGINT/SIGTERM or
    ``max_seconds`` after ``started`` (monotonic s), then close it. No page: nothing to do."""
    page = next((o for o in service.observers if getattr(o, "lingers", False)), None)
    if page is None:
        return
    try:
        if service.stats.stop_reason != "end of replay":
            return
        service.device_state = "replay over"
        # the line below tells a reader the final state is served: wait until it is
        page.page.wait_published(page.state.final(service), timeout=5.0)
        stopped: list[str] = []
        for sig, label in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
            signal.signal(sig, lambda s, f, label=label: stopped.append(label))
        print(f"streamcal {name}: replay over; the live page stays at {page.page.url} "
              "until Ctrl-C", file=sys.stderr, flush=True)
        while not stopped:
            if max_seconds is not None and time.monotonic() - started >= max_seconds:
                stopped.append(f"--max-seconds {max_seconds:g} reached")
                break
            time.sleep(0.1)
        print(f"streamcal {name}: live page closed ({stopped[0]})", file=sys.stderr, flush=True)
    finally:
        page.close_page()
