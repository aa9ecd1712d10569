"""The streaming calibrator: buffer, running sphere estimate, policy, worker fit, guard, store.

Per block of samples (DESIGN §1)::

    block ─▶ SphereStats.update          (instant coarse estimate, O(1) memory)
          ─▶ CoverageBuffer.insert       (bounded, newest per direction cell)
          ─▶ drift check                 (recent window vs the calibration in use)
          ─▶ pick up a finished fit ─▶ AcceptanceGuard ─▶ CalibrationStore
          ─▶ RecalPolicy: start a fit?  ─▶ worker thread runs fitter(snapshot)

Ingest never waits for a fit (DESIGN §4.1): the fit runs on a worker thread, at most one at a
time, and its result is picked up by a later ``ingest`` or ``poll``. Small blocks are staged in a
preallocated array and processed ``stage`` samples at a time, so the per-sample cost of feeding
one sample per call stays small; ``poll()`` processes what is staged.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration
from ..fit.sphere_stream import SphereStats
from .coverage import CoverageBuffer, CoverageReport, Snapshot
from .guard import AcceptanceGuard, Decision, holdout_error, radius_of
from .policy import RecalPolicy

_IMU = {"ax": ("accel", 0), "ay": ("accel", 1), "az": ("accel", 2),
        "gx": ("gyro", 0), "gy": ("gyro", 1), "gz": ("gyro", 2)}
#: Coverage milestones reported as events (fractions of the sphere).
MILESTONES = (0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9, 0.95)


@dataclass(frozen=True)
class Event:
    """Something the calibrator did or noticed.

    ``kind``: ``loaded``, ``load_problem``, ``coverage``, ``fit_started``, ``fit_failed``,
    ``accepted``, ``rejected``, ``discarded``, ``drift``, ``forgot``, ``stored``, ``store_error``.
    ``t`` is the sample time (s) at which it happened, ``data`` its figures (JSON-ready).
    """

    kind: str
    message: str
    data: dict = field(default_factory=dict)
    t: float | None = None

    def to_dict(self) -> dict:
        return {"event": self.kind, "t": self.t, "message": self.message, **self.data}


def default_fitter(model=DEFAULT_MODEL, kernel: str = "cauchy"):
    """``fitter(snapshot) -> Calibration`` running :func:`streamcal.fit.fit` on the stored
    samples (with their covariates when the model has effects beyond K and b)."""

    def fit_snapshot(snap: Snapshot) -> Calibration:
        from ..fit import fit

        if set(model) <= {"hard_iron", "soft_iron", "scale"}:
            return fit(snap.m, model=tuple(model), kernel=kernel)
        return fit(snap.to_track(), model=tuple(model), kernel=kernel)

    return fit_snapshot


class _Job:
    def __init__(self, fit_set: Snapshot, holdout: Snapshot, coverage: float, t: float):
        self.fit_set, self.holdout, self.coverage, self.t = fit_set, holdout, coverage, t
        self.done = threading.Event()
        self.result: Calibration | None = None
        self.error: BaseException | None = None
        self.obsolete = False

    def run(self, fitter) -> None:
        try:
            self.result = fitter(self.fit_set)
        except BaseException as exc:  # reported as a fit_failed event, never lost
            self.error = exc
        finally:
            self.done.set()


class StreamingCalibrator:
    """Calibrate a magnetometer (or accelerometer) from a stream of :class:`SampleBlock`.

    Args:
        fitter: ``fitter(snapshot) -> Calibration``; default :func:`default_fitter`.
        store: a :class:`~streamcal.stream.store.CalibrationStore` (loads the calibration in use
            at start, records accepted ones) or None.
        buffer, policy, guard: the parts; defaults are built from their defaults.
        unit: sensor unit of the samples (``"uT"`` …), written into accepted calibrations.
        stage: samples staged before processing (per-call overhead amortised over them).
        holdout_every: one stored sample in this many is held out of each fit for the guard.
        coarse_every: samples between refreshes of the running sphere estimate.
        synchronous: run fits inline (deterministic offline replays); default is a worker thread.

    Usage::

        cal = StreamingCalibrator(store=CalibrationStore(state_dir))
        for block in source:
            for event in cal.ingest(block):
                print(event.message)
            out = cal.apply(block)          # (n,3) calibrated field, sensor unit
    """

    def __init__(self, *, fitter=None, store=None, buffer: CoverageBuffer | None = None,
                 policy: RecalPolicy | None = None, guard: AcceptanceGuard | None = None,
                 model=DEFAULT_MODEL, unit: str = "uT", stage: int = 64, holdout_every: int = 5,
                 coarse_every: int = 200, coarse_min: int = 100, synchronous: bool = False):
        self.fitter = fitter if fitter is not None else default_fitter(model)
        self.store = store
        self.buffer = buffer if buffer is not None else CoverageBuffer()
        self.policy = policy if policy is not None else RecalPolicy()
        self.guard = guard if guard is not None else AcceptanceGuard()
        self.unit = unit
        self.holdout_every = int(holdout_every)
        self.coarse_every = int(coarse_every)
        self.coarse_min = int(coarse_min)
        self.synchronous = synchronous
        self.stats = SphereStats()
        self.coarse: tuple[np.ndarray, float] | None = None
        self.stale = False
        self.n_ingested = 0
        self.n_fits = 0
        self._cal: Calibration | None = None
        self._job: _Job | None = None
        self._since_coarse = 0
        self._milestone = 0.0
        self._t_last = float("nan")
        names = self.buffer.covariate_names
        self._stage_m = np.empty((max(1, stage), 3))
        self._stage_t = np.empty(max(1, stage))
        self._stage_cov = np.empty((max(1, stage), len(names)))
        self._held = np.full(len(names), np.nan)
        self._n_staged = 0
        self._pending: list[Event] = []
        if store is not None:
            self._load()

    # -- public -------------------------------------------------------------------------------
    @property
    def calibration(self) -> Calibration | None:
        """The calibration in use (None before the first is accepted or loaded)."""
        return self._cal

    @property
    def coverage(self) -> CoverageReport:
        return self.buffer.report()

    @property
    def fit_in_flight(self) -> bool:
        return self._job is not None

    def ingest(self, block) -> list:
        """Take a :class:`SampleBlock`; returns the events it caused (may be empty)."""
        ok = block.mag_valid
        m = np.asarray(block.mag)[ok]
        n = len(m)
        self.n_ingested += n
        if n == 0:
            return self._drain_pending()
        t = np.asarray(block.t, dtype=float)[ok]
        cov = self._covariate_matrix(block, ok, n)
        k, cap = self._n_staged, len(self._stage_t)
        if k + n < cap:
            self._stage_m[k:k + n] = m
            self._stage_t[k:k + n] = t
            self._stage_cov[k:k + n] = cov
            self._n_staged = k + n
            return self._drain_pending()
        if k:
            m = np.concatenate([self._stage_m[:k], m])
            t = np.concatenate([self._stage_t[:k], t])
            cov = np.concatenate([self._stage_cov[:k], cov])
            self._n_staged = 0
        return self._drain_pending() + self._process(m, t, cov)

    def poll(self) -> list:
        """Process staged samples and pick up a finished fit; returns the events."""
        events = self._drain_pending()
        k = self._n_staged
        if k:
            self._n_staged = 0
            events += self._process(self._stage_m[:k].copy(), self._stage_t[:k].copy(),
                                    self._stage_cov[:k].copy())
        else:
            events += self._collect()
        return events

    def drain(self, timeout: float | None = None) -> list:
        """:meth:`poll`, then wait (up to ``timeout`` s) for the fit in flight and pick it up."""
        events = self.poll()
        job = self._job
        if job is not None and job.done.wait(timeout):
            events += self._collect()
        return events

    def apply(self, block, unit_vectors: bool = False) -> np.ndarray:
        """Calibrated samples of ``block`` (n,3): the field in the sensor unit (``|B| x``), or unit
        directions ``x`` with ``unit_vectors``. Uses the running sphere estimate before the first
        calibration; NaN rows where there is no magnetometer sample or no estimate yet."""
        m = np.asarray(block.mag, dtype=float)
        out = np.full(m.shape, np.nan)
        ok = block.mag_valid
        cal = self._cal
        if cal is not None:
            cov = _block_covariates(block) if cal.effects else None
            x = cal.apply(m[ok], {k: v[ok] for k, v in cov.items()} if cov else None)
            out[ok] = x if unit_vectors else x * (cal.field or radius_of(cal))
        elif self.coarse is not None:
            c, R = self.coarse
            out[ok] = (m[ok] - c) / R if unit_vectors else m[ok] - c
        return out

    def close(self, timeout: float | None = None) -> list:
        """Process what is staged and wait for a fit in flight; returns the last events."""
        return self.drain(timeout)

    # -- the per-block path -------------------------------------------------------------------
    def _process(self, m, t, cov) -> list:
        events: list[Event] = []
        self._t_last = t_now = float(t[-1])
        self.stats.update(m)
        self._since_coarse += len(m)
        # The coarse estimate frames directions until a calibration is in use; after that it
        # is only the guard's reference radius and is refreshed ten times less often.
        calibrated = self._cal is not None and not self.stale
        if self._since_coarse >= self.coarse_every * (10 if calibrated else 1):
            self._update_coarse()
        cov_dict = {name: cov[:, k] for k, name in enumerate(self.buffer.covariate_names)}
        stored, new_cells = self.buffer.insert(m, t, cov_dict)
        self.policy.note(stored, new_cells)
        if self._cal is not None and not self.stale:
            self._check_drift(m, t, cov_dict, events)
        self._milestones(events)
        events += self._collect()
        if self._job is None:
            request = self.policy.want_fit(
                calibrated=self._cal is not None and not self.stale,
                coverage=self.buffer.fraction, n_samples=self.buffer.n_samples,
                n_cells=self.buffer.cells.n_cells, capacity=self.buffer.capacity, t_now=t_now)
            if request is not None:
                self.policy.requested(t_now)
                events += self._submit(request, t_now)
        return events

    def _update_coarse(self) -> None:
        self._since_coarse = 0
        if self.stats.n < self.coarse_min:
            return
        try:
            c, R = self.stats.fit()
        except Exception:           # too few directions yet: keep the previous estimate
            return
        if not (np.all(np.isfinite(c)) and np.isfinite(R) and R > 0):
            return
        previous, self.coarse = self.coarse, (c, R)
        if self._cal is None or self.stale:
            moved = previous is None or (np.linalg.norm(c - previous[0]) > 0.05 * R
                                         or abs(R - previous[1]) > 0.05 * R)
            if moved or self.stale and self._frame_is_cal:
                self._set_frame(c, np.eye(3) / R, from_cal=False)

    _frame_is_cal = False

    def _set_frame(self, center, A, from_cal: bool) -> None:
        self.buffer.set_frame(center, A)
        if from_cal:
            self._cal_AT = np.asarray(A).T.copy()
            self._cal_R = radius_of(self._cal)
        self._frame_is_cal = from_cal
        self._milestone = _floor_milestone(self.buffer.fraction)

    def _check_drift(self, m, t, cov, events) -> None:
        cal = self._cal
        if cal.effects:
            x = cal.apply(m, {"t": t, **cov})
        else:
            x = (m - cal.b) @ self._cal_AT
        self.policy.observe(np.abs(np.sqrt(np.einsum("nk,nk->n", x, x)) - 1.0), t)
        found = self.policy.drift(cal.rms, self._cal_R)
        if found is None:
            return
        stat, limit, onset = found
        events.append(Event("drift", f"field no longer fits the calibration: median relative "
                            f"error {stat:.3f} > {limit:.3f} since t={onset:.2f} s "
                            f"(new hard iron or a magnet nearby?)",
                            {"value": stat, "limit": limit, "onset": onset}, t[-1]))
        dropped = self.buffer.forget_before(onset)
        kept = self.buffer.snapshot()
        self.stats.reset()
        self.stats.update(kept.m)
        self.coarse = None
        self._since_coarse = 0
        self.policy.restart()
        self.stale = True
        self._milestone = _floor_milestone(self.buffer.fraction)
        if self._job is not None:
            self._job.obsolete = True
        events.append(Event("forgot", f"forgot {dropped} stored samples older than "
                            f"t={onset:.2f} s; kept {len(kept)}; calibration in use is stale "
                            f"until a new one is accepted",
                            {"dropped": dropped, "kept": len(kept), "onset": onset}, t[-1]))

    def _milestones(self, events) -> None:
        frac = self.buffer.fraction
        reached = _floor_milestone(frac)
        if reached > self._milestone:
            self._milestone = reached
            report = self.buffer.report()
            events.append(Event("coverage", f"coverage {100 * frac:.0f}% of the sphere; "
                                f"largest gap {report.empty_cap_deg:.0f}°: {report.hint}",
                                report.to_dict(), self._t_last))

    # -- fitting ------------------------------------------------------------------------------
    def _submit(self, request, t_now) -> list:
        snap = self.buffer.snapshot()
        held = (np.arange(len(snap)) + self.n_fits) % self.holdout_every == 0
        job = _Job(snap.subset(~held), snap.subset(held), self.buffer.fraction, t_now)
        self.n_fits += 1
        self._job = job
        event = Event("fit_started", f"fit #{self.n_fits} started ({request.reason}): "
                      f"{len(job.fit_set)} samples, {len(job.holdout)} held out, coverage "
                      f"{100 * job.coverage:.0f}%",
                      {"reason": request.reason, "fit": self.n_fits, "n_fit": len(job.fit_set),
                       "n_holdout": len(job.holdout), **request.data}, t_now)
        if self.synchronous:
            job.run(self.fitter)
            return [event] + self._collect()
        threading.Thread(target=job.run, args=(self.fitter,), name="streamcal-fit",
                         daemon=True).start()
        return [event]

    def _collect(self) -> list:
        job = self._job
        if job is None or not job.done.is_set():
            return []
        self._job = None
        t = self._t_last
        if job.obsolete:
            return [Event("discarded", "fit result discarded: the environment changed while it "
                          "ran", {"reason": "environment_changed"}, t)]
        if job.error is not None:
            return [Event("fit_failed", f"fit failed: {job.error}",
                          {"error": type(job.error).__name__}, t)]
        cand = job.result.replace(unit=self.unit, coverage=round(float(job.coverage), 4))
        current = self._cal if self._cal is not None else self._coarse_calibration()
        ref_R = self.coarse[1] if self.coarse is not None else None
        decision = self.guard.check(cand, job.holdout.m, _cov_with_t(job.holdout), current, ref_R)
        data = {**decision.to_dict(), "K": cand.K.round(6).tolist(), "b": cand.b.round(6).tolist(),
                "rms": _finite(cand.rms), "coverage_at_fit": cand.coverage}
        if not decision.accepted:
            return [Event("rejected", f"candidate rejected: {_reason_text(decision)}", data, t)]
        self._cal = cand
        self.stale = False
        self.policy.reset_window()
        self._set_frame(cand.b, np.linalg.inv(cand.K), from_cal=True)
        events = [Event("accepted", f"calibration accepted ({_reason_text(decision)}): rms "
                        f"{cand.rms:.3g} {self.unit}, b = {np.round(cand.b, 2).tolist()}",
                        data, t)]
        if self.store is not None:
            try:
                path = self.store.save(cand)
                events.append(Event("stored", f"saved {self.store.current_path} ({path.name})",
                                    {"path": str(self.store.current_path)}, t))
            except Exception as exc:    # keep calibrating; the old file stays valid
                events.append(Event("store_error", f"could not save the calibration: {exc}",
                                    {}, t))
        return events

    def _coarse_calibration(self) -> Calibration | None:
        if self.coarse is None:
            return None
        c, R = self.coarse
        return Calibration(K=R * np.eye(3), b=c, model=("hard_iron",), method="sphere_stream",
                           unit=self.unit, n=self.stats.n)

    def _load(self) -> None:
        result = self.store.load()
        for problem in result.problems:
            if not problem.endswith(": missing") or result.fell_back:
                self._pending.append(Event("load_problem", problem, {}))
        if result.calibration is not None:
            self._cal = result.calibration
            self._set_frame(self._cal.b, np.linalg.inv(self._cal.K), from_cal=True)
            how = " (fallback: the current file was missing or damaged)" if result.fell_back else ""
            self._pending.append(Event("loaded", f"calibration in use loaded from {result.path}{how}",
                                       {"path": str(result.path), "fell_back": result.fell_back}))

    def _drain_pending(self) -> list:
        out, self._pending = self._pending, []
        return out

    def _covariate_matrix(self, block, ok, n) -> np.ndarray:
        """Covariates at the magnetometer rows (n, P). Sensors run at different rates, so a
        covariate missing on a mag row takes its last value seen (sample and hold)."""
        names = self.buffer.covariate_names
        cov = np.full((n, len(names)), np.nan)
        for k, name in enumerate(names):
            if name == "temp":
                src = block.temp
            elif name in _IMU:
                arr = getattr(block, _IMU[name][0])
                src = None if arr is None else np.asarray(arr)[:, _IMU[name][1]]
            else:
                src = block.aux.get(name)
            if src is None:
                continue
            src = np.asarray(src, dtype=float)
            seen = np.isfinite(src)
            idx = np.maximum.accumulate(np.where(seen, np.arange(len(src)), -1))
            held = np.where(idx >= 0, src[np.maximum(idx, 0)], self._held[k])
            if seen.any():
                self._held[k] = src[seen][-1]
            cov[:, k] = held[ok]
        return cov


def _floor_milestone(frac: float) -> float:
    passed = [m for m in MILESTONES if frac >= m]
    return passed[-1] if passed else 0.0


def _cov_with_t(snap: Snapshot) -> dict:
    return {"t": snap.t, **snap.covariates}


def _block_covariates(block) -> dict:
    cov = {"t": np.asarray(block.t, dtype=float)}
    if block.temp is not None:
        cov["temp"] = np.asarray(block.temp, dtype=float)
    for name, (group, axis) in _IMU.items():
        arr = getattr(block, group)
        if arr is not None:
            cov[name] = np.asarray(arr, dtype=float)[:, axis]
    cov.update({k: np.asarray(v, dtype=float) for k, v in block.aux.items()})
    return cov


def _finite(v):
    v = float(v)
    return v if np.isfinite(v) else None


def _reason_text(decision: Decision) -> str:
    if decision.value is None:
        return decision.reason
    if decision.limit is None:
        return f"{decision.reason} = {decision.value:.4g}"
    return f"{decision.reason}: {decision.value:.4g} vs limit {decision.limit:.4g}"
