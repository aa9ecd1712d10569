"""What the live page shows: small copies taken on the service loop, the JSON built elsewhere.

::

    Service loop (ingest thread)                       publisher thread (:mod:`.http_page`)
    on_block ── at most every ``period_s`` ──▶ capture ──▶ LiveState.build() ──▶ JSON ──▶ clients
    on_events ── fit and disturbance events ─┘  (copies under a lock)  (largest gap, hint, serialise)

The loop pays for one ``time.monotonic()`` per block and, every ``period_s`` (0.25 s), a copy of
the coverage buffer's stored readings (at most cells × slots rows, 1200 × 3 floats by default),
its occupied cells and a few counters. Directions, the largest empty cap (the O(probes × samples)
part) and the JSON are computed by :meth:`LiveState.build` on the caller's thread, never on the
loop. Only public attributes of the calibrator and its buffer are read.

Snapshot keys (JSON, what ``/events`` sends and ``/state.json`` returns):

- ``seq``: capture number; ``uptime_s``: wall seconds since the page started.
- ``coverage``: occupied cells / all cells (0..1); ``cells``: ``{"counts": [...], "z_edges":
  [...]}`` the equal-area partition (:class:`~streamcal.sphere_cells.SphereCells`: cells per
  band north first, band edges in z) and ``occupied``: one ``"0"``/``"1"`` per cell;
  ``n_samples``; ``gap``: ``{"deg", "center": [x, y, z]}`` the largest empty cap (body axes of
  the current frame); ``hint``: where to turn next (the same words as the terminal report);
  ``directions``: at most ``MAX_DIRECTIONS`` of the stored samples as unit vectors ``[x, y, z]``
  in the same frame (evenly picked; empty until a sphere frames them), the 3-D sphere's dots.
- ``magnitude``: ``{"t": [...], "raw": [...], "calibrated": [...], "unit"}`` over the last
  ``window_s`` (60 s): wall seconds relative to now (≤ 0), the median ``‖m‖`` of the latest
  block before calibration and the median ``‖field‖`` after it (null before the first
  calibration), both in ``unit`` (``"uT"`` for µT).
- ``calibration``: null, or ``{"version", "rms", "residual", "unit", "field", "coverage",
  "method", "model", "created", "stale"}`` — ``rms`` is the sensor estimation error over inliers
  (``residual`` names it), ``stale`` true after an environment change until a refit.
- ``fits``: ``{"accepted", "rejected", "failed", "in_flight", "recent": [{"kind", "t", "reason",
  "message"}]}`` (``reason``: the guard's named rule).
- ``disturbance``: ``{"held_total", "held_recent", "open", "recent": [...]}`` — samples held
  back so far and in the last ``period_s``·8 s; ``open`` is true while samples are being held.
- ``reference``: the local field from ``--lat/--lon`` beside the calibration's field and the
  median dip of the calibrated field below the plane normal to the accelerometer's gravity over
  the last ``window_s`` (block medians; hand motion tilts single blocks by degrees): the
  ``reference_field`` object of ``diagnose --json`` (:func:`streamcal.geomag.compare`), or
  ``{"source": null, "reason"}`` without a location.
- ``ring``: null, or ``{"down", "dip_deg", "source", "field", "off_deg"}``: at the newest
  block's roll and pitch (``down``: unit gravity, body axes) the field must lie on the circle
  of directions ``dip_deg`` below the plane normal to ``down`` (the model's inclination with a
  location, else the fitted dip); ``field`` the newest block's calibrated direction and
  ``off_deg`` its angle off the circle (null before a calibration).
- ``device``: ``{"state", "samples", "samples_per_s", "bus_errors", "restarts", "counters"}``
  (``bus_errors``: I²C failures, or frames lost on serial; ``restarts``: board restarts seen).
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np

from ..geomag import NO_LOCATION, compare, dip_deg
from ..sphere_cells import hint, largest_empty_cap
from ..stream.coverage import not_measured

#: The residual the calibration's ``rms`` is computed on.
RMS_RESIDUAL = "sensor estimation error over inliers (paper eq. 41)"
#: The most stored directions a snapshot carries (about 7 kB of JSON).
MAX_DIRECTIONS = 300
_FIT_KINDS = ("accepted", "rejected", "fit_failed", "discarded", "recalled")
_DISTURB_KINDS = ("disturbance", "drift", "forgot")


class LiveState:
    """Service observer (``Service(observers=[state])``) keeping what the page needs.

    Args:
        period_s: least interval between two captures on the loop (s).
        window_s: how much of the field magnitude history is kept (s).
        clock: wall clock (s), monotonic.
        reference: the local field (:func:`streamcal.geomag.wmm_field`), None without a location.
    """

    def __init__(self, period_s: float = 0.25, window_s: float = 60.0, clock=time.monotonic,
                 reference: dict | None = None):
        self.period_s, self.window_s, self.clock = float(period_s), float(window_s), clock
        self.reference = reference
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._captured: dict | None = None
        self._seq = 0
        self._next = -math.inf
        self._start = clock()
        n = int(window_s / max(period_s, 0.05)) + 4
        self._mag = deque(maxlen=n)                       # (wall s, raw, calibrated)
        self._rate = deque(maxlen=16)                     # (wall s, samples ingested)
        self._held = deque(maxlen=9)                      # (wall s, n_held)
        self._dips = deque(maxlen=n)                      # (wall s, median dip of a block, °)
        self._ring = None                                 # (down, field direction) latest block
        self._fit_events = deque(maxlen=12)
        self._disturb_events = deque(maxlen=8)
        self.closed = False
        self._ended = False
        self.capture_errors = 0
        self.gap_every_s = 0.5
        self._gap = None                                  # (occupied bytes, wall s, center, deg)

    # -- observer side (the loop's thread) -----------------------------------------------------
    def on_events(self, events) -> None:
        picked = [(e.kind, e) for e in events if e.kind in _FIT_KINDS + _DISTURB_KINDS]
        if not picked:
            return
        with self._lock:
            for kind, e in picked:
                item = {"kind": kind, "t": _num(e.t), "message": e.message,
                        "reason": (e.data or {}).get("reason") or (e.data or {}).get("outcome")}
                (self._fit_events if kind in _FIT_KINDS else self._disturb_events).append(item)

    def on_block(self, service, block) -> None:
        now = self.clock()
        if now < self._next:
            return
        self._next = now + self.period_s
        try:
            captured = self._capture(service, block, now)
        except Exception:        # the page must never take the service down
            self.capture_errors += 1
            return
        with self._changed:
            self._captured = captured
            self._seq += 1
            self._changed.notify_all()

    def _ring_inputs(self, now: float, field, accel) -> None:
        """The block's dip, its median down direction and median calibrated field direction."""
        dip, _ = dip_deg(field, -accel)
        if dip is None:
            return
        self._dips.append((now, dip))
        down = -np.median(accel / np.linalg.norm(accel, axis=1, keepdims=True), axis=0)
        f = field[np.isfinite(field).all(axis=1)]
        f = np.median(f / np.linalg.norm(f, axis=1, keepdims=True), axis=0)
        self._ring = (down / np.linalg.norm(down), f / np.linalg.norm(f))

    def final(self, service) -> int:
        """One last capture after the loop ended (a replay over, its page kept up): taken now
        whatever the period, with no samples arriving any more (0 samples/s); returns its
        capture number."""
        self._ended = True
        self._next = -math.inf
        self.on_block(service, None)
        with self._lock:
            return self._seq

    def close(self) -> None:
        with self._changed:
            self.closed = True
            self._changed.notify_all()

    def _capture(self, service, block, now: float) -> dict:
        cal = service.calibrator
        buf = cal.buffer
        raw = calibrated = None
        if block is not None and len(block):
            m = np.asarray(block.mag, dtype=float)
            norm = np.linalg.norm(m, axis=1)
            ok = np.isfinite(norm)
            if ok.any():
                raw = float(np.median(norm[ok]))
                vec = cal.apply(block)
                f = np.linalg.norm(vec, axis=1)
                f = f[np.isfinite(f)]
                # before the first calibration apply() scales by the running sphere estimate:
                # not a calibrated field, so no "after calibration" figure
                if cal.calibration is not None and len(f):
                    calibrated = float(np.median(f))
                if block.accel is not None and len(f):
                    self._ring_inputs(now, vec, np.asarray(block.accel, dtype=float))
        if raw is not None:
            self._mag.append((now, raw, calibrated))
        self._rate.append((now, service.stats.samples))
        self._held.append((now, cal.n_held))
        c = cal.calibration
        return {
            "now": now, "stored": buf.stored_mag(), "center": buf.center.copy(),
            "A": buf.A.copy(), "occupied": buf.occupied, "fraction": float(buf.fraction),
            "unframed": buf.unframed,
            "cells": buf.cells, "calibration": c, "cal_version": service.cal_version,
            "stale": bool(getattr(cal, "stale", False)), "in_flight": bool(cal.fit_in_flight),
            "event_counts": dict(service.stats.events), "samples": service.stats.samples,
            "device_state": service.device_state, "counters": dict(service.source.counters()),
            "mag": list(self._mag), "rate": list(self._rate), "held": list(self._held),
            "fit_events": list(self._fit_events), "disturb_events": list(self._disturb_events),
            "unit": getattr(cal, "unit", "uT"), "reference": self.reference,
            "dips": [d for t, d in self._dips if now - t <= self.window_s],
            "ring": self._ring, "ended": self._ended,
        }

    # -- reader side (any thread) ----------------------------------------------------------------
    def wait(self, seq: int, timeout: float) -> int:
        """Block until a capture newer than ``seq`` exists (or ``timeout`` s, or close); returns
        the latest capture number."""
        with self._changed:
            if self._seq <= seq:
                self._changed.wait(timeout)     # closed: still waits, a reader must not spin
            return self._seq

    def build(self) -> dict | None:
        """The snapshot (module docstring) of the latest capture; None before the first."""
        with self._lock:
            cap, seq = self._captured, self._seq
        if cap is None:
            return None
        return _snapshot(cap, seq, self._start, self._largest_gap(cap))

    def _largest_gap(self, cap: dict) -> tuple[np.ndarray, float]:
        """The largest empty cap of the captured directions, recomputed only when the occupied
        cells changed and at most every ``gap_every_s`` (it costs O(probes × stored samples),
        tens of ms on a busy Pi; the terminal report computes the same figure)."""
        if cap["unframed"]:     # not shown: the directions mean nothing yet
            return np.full(3, np.nan), float("nan")
        key = np.packbits(np.asarray(cap["occupied"], bool)).tobytes()
        if self._gap is not None and (self._gap[0] == key
                                      or cap["now"] - self._gap[1] < self.gap_every_s):
            return self._gap[2], self._gap[3]
        m = cap["stored"]
        d = np.empty((0, 3))
        if len(m):
            x = (m - cap["center"]) @ cap["A"].T
            norm = np.linalg.norm(x, axis=1)
            d = x[norm > 0] / norm[norm > 0, None]
        center, radius = largest_empty_cap(d)
        self._gap = (key, cap["now"], center, radius)
        return center, radius


def _snapshot(cap: dict, seq: int, start: float, gap) -> dict:
    now = cap["now"]
    m = cap["stored"]
    center, radius = gap
    cells = cap["cells"]
    occupied = np.asarray(cap["occupied"], bool)
    mag = cap["mag"]
    keep = [row for row in mag if now - row[0] <= 60.0]
    rate = cap["rate"]
    recent = [r for r in rate if now - r[0] <= 2.0] or rate
    sps = 0.0
    if len(recent) >= 2 and recent[-1][0] > recent[0][0] and not cap["ended"]:
        sps = (recent[-1][1] - recent[0][1]) / (recent[-1][0] - recent[0][0])
    held = cap["held"]
    held_recent = held[-1][1] - held[0][1] if len(held) >= 2 else 0
    counters = cap["counters"]
    counts = cap["event_counts"]
    c = cap["calibration"]
    calib = None
    if c is not None:
        calib = {"version": cap["cal_version"], "rms": _num(c.rms), "residual": RMS_RESIDUAL,
                 "unit": c.unit, "field": _num(c.field), "coverage": _num(c.coverage),
                 "method": c.method, "model": list(c.model), "created": c.created,
                 "stale": cap["stale"]}
    framed = not cap["unframed"]
    if not framed:      # the directions mean nothing yet: no coverage, no seen cells, no gap
        occupied = np.zeros_like(occupied)
    return {
        "seq": seq, "uptime_s": round(now - start, 2),
        "coverage": round(cap["fraction"], 4) if framed else None, "n_samples": int(len(m)),
        "cells": {"counts": cells.counts.tolist(),
                  "z_edges": [round(float(z), 6) for z in cells.z_edges]},
        "occupied": "".join("1" if o else "0" for o in occupied.tolist()),
        "gap": {"deg": round(radius, 1), "center": [round(float(v), 3) for v in center]}
        if framed else None,
        "directions": _directions(cap) if framed else [],
        "hint": hint(center, radius, cap["fraction"]) if framed
        else not_measured(cap["unframed"]),
        "magnitude": {"t": [round(r[0] - now, 2) for r in keep],
                      "raw": [round(r[1], 3) for r in keep],
                      "calibrated": [None if r[2] is None else round(r[2], 3) for r in keep],
                      "unit": cap["unit"]},
        "calibration": calib,
        "fits": {"accepted": counts.get("accepted", 0), "rejected": counts.get("rejected", 0),
                 "failed": counts.get("fit_failed", 0), "in_flight": cap["in_flight"],
                 "recent": cap["fit_events"]},
        "disturbance": {"held_total": held[-1][1] if held else 0, "held_recent": held_recent,
                        "open": held_recent > 0, "drifts": counts.get("drift", 0),
                        "recent": cap["disturb_events"]},
        "reference": _reference(cap, c),
        "ring": _ring(cap, c),
        "device": {"state": cap["device_state"], "samples": cap["samples"],
                   "samples_per_s": round(sps, 1),
                   "bus_errors": counters.get("bus_errors", counters.get("lost", 0)),
                   "bus_errors_name": "bus errors" if "bus_errors" in counters else "frames lost",
                   "restarts": counters.get("restarts", counters.get("reinits", 0)),
                   "counters": {k: v for k, v in counters.items()
                                if isinstance(v, (int, float))}},
    }


def _directions(cap: dict) -> list:
    """Up to :data:`MAX_DIRECTIONS` stored samples, evenly picked, as unit vectors (3 decimals)
    in the frame of the running sphere (``center``, ``A``)."""
    m = cap["stored"]
    if not len(m):
        return []
    pick = m[np.unique(np.linspace(0, len(m) - 1, min(len(m), MAX_DIRECTIONS)).astype(int))]
    x = (pick - cap["center"]) @ cap["A"].T
    norm = np.linalg.norm(x, axis=1)
    ok = np.isfinite(norm) & (norm > 0)
    return np.round(x[ok] / norm[ok, None], 3).tolist()


def _reference(cap: dict, c) -> dict:
    ref = cap["reference"]
    if ref is None:
        return compare(None, None, "", reason=NO_LOCATION)
    dips = cap["dips"]
    dip = spread = None
    if dips:
        dip = float(np.median(dips))
        spread = float(1.4826 * np.median(np.abs(np.asarray(dips) - dip)))
    field = None if c is None else (c.field or c.radius)
    return compare(ref, field, c.unit if c is not None else cap["unit"], dip, spread)


def _ring(cap: dict, c) -> dict | None:
    """Where the field must point at the current roll and pitch: the circle of directions at
    ``dip_deg`` below the plane normal to ``down`` (both body axes), and how far the newest
    block's calibrated direction lies off it (°)."""
    if cap["ring"] is None:
        return None
    down, f = cap["ring"]
    ref = cap["reference"]
    if ref is not None:
        dip, source = ref["inclination_deg"], f"{ref['source']} inclination"
    elif cap["dips"]:
        dip, source = float(np.median(cap["dips"])), "fitted dip (median, last minute)"
    else:
        return None
    off = None
    if c is not None:
        off = abs(math.degrees(math.asin(float(np.clip(f @ down, -1, 1)))) - dip)
    return {"down": [round(float(v), 4) for v in down], "dip_deg": round(dip, 2),
            "source": source, "field": None if c is None else [round(float(v), 4) for v in f],
            "off_deg": _num(off)}


def _num(v):
    if v is None:
        return None
    v = float(v)
    return round(v, 6) if math.isfinite(v) else None
