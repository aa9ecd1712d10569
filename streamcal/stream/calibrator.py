"""The streaming calibrator: buffer, running sphere estimate, policy, worker fit, guard, store.

Per stage of samples (DESIGN §1)::

    ingest(block) ─▶ Stage (preallocated; a few µs per call, nothing else when not full)
    stage full    ─▶ calibration in force: hold back disagreeing samples (Quarantine)
                     none in force: SphereStats.update (instant coarse estimate, O(1) memory)
                  ─▶ CoverageBuffer.insert       (bounded, newest per direction cell)
                  ─▶ drift window               (recent samples vs the calibration in use, or
                                                  the running sphere estimate before one, on the
                                                  directions it was fitted on): disturbance
                                                  opened / ended / an environment change
                  ─▶ while stale: recall check   (does a remembered calibration fit again?)
                  ─▶ pick up a finished fit ─▶ AcceptanceGuard ─▶ CalibrationStore
                  ─▶ RecalPolicy: start a fit?  ─▶ worker thread runs fitter(snapshot)
                  ─▶ StatusReporter: the state in words, every few seconds of sample time

Ingest never waits for a fit (DESIGN §4.1): one fit at a time runs on a worker thread and a
later ``ingest`` or ``poll`` picks it up (``synchronous=True``, for reproducible replays: it runs
when due and is picked up at once). The parts' modules: :mod:`.clock`, :mod:`.fitworker`,
:mod:`.reference` (hold-back), :mod:`.tracker` (disturbances and environment changes, rules in
:mod:`.disturbance`), :mod:`.running_sphere`, :mod:`.recall`, :mod:`.environments`,
:mod:`.status`. Rows are staged ``stage`` at a time (default 256: 2.6 s at 100 Hz, 0.9 s at
286 Hz), so fits start, finished fits are picked up and drift is judged at most one stage late;
a larger block is processed at once, with what was staged. ``poll()`` processes what is staged
(call it when the source is idle). A candidate always has to beat the calibration in use on
held-out samples, so a worse calibration is never accepted.
"""
from __future__ import annotations

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration
from .coverage import CoverageBuffer, CoverageReport
from .blocks import apply_block, disagreement
from .clock import MonotoneClock
from .disturbance import DisturbanceRule
from . import events as ev
from .events import Event
from .fitworker import FitJob, FitWorker, default_fitter
from .environments import EnvironmentLog
from .guard import AcceptanceGuard
from .policy import RecalPolicy
from .recall import Recaller
from .reference import Reference
from .running_sphere import NO_ESTIMATE, RunningSphere, sphere_of_samples
from .staging import Stage
from .status import StatusReporter
from .tracker import DisturbanceTracker


class StreamingCalibrator:
    """Calibrate a magnetometer (or accelerometer) from a stream of :class:`SampleBlock`.

    Args:
        fitter: ``fitter(snapshot) -> Calibration``; default :func:`default_fitter`.
        store: a :class:`~streamcal.stream.store.CalibrationStore` (loads the calibration in use
            at start, records accepted ones) or None.
        buffer, policy, guard: the parts; defaults are built from their defaults.
        unit: sensor unit of the samples (``"uT"`` …), written into accepted calibrations.
        stage: rows staged before processing (per-call overhead amortised over them; fits and
            drift checks are at most this many rows late).
        holdout_every: one stored sample in this many is held out of each fit for the guard.
        coarse_every: samples between refreshes of the running sphere estimate (before the
            first calibration and while stale).
        remember: accepted calibrations remembered for recall after an environment change.
        recall_checks: consecutive drift-window checks (one per quarter window) a remembered
            calibration must pass to be recalled.
        disturbance: the :class:`~streamcal.stream.disturbance.DisturbanceRule` (when a
            disagreement is a transient, when an environment change); default its defaults.
        hold: capacity (samples) of the ring of held-back samples.
        coarse_judge_coverage: sphere fraction the buffer must cover before the running sphere
            estimate watches for environment changes (before the first calibration).
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
                 model=DEFAULT_MODEL, unit: str = "uT", stage: int = 256, holdout_every: int = 5,
                 coarse_every: int = 200, coarse_min: int = 100, remember: int = 4,
                 recall_checks: int = 5, disturbance: DisturbanceRule | None = None,
                 hold: int = 2048, coarse_judge_coverage: float = 0.1,
                 synchronous: bool = False):
        self.fitter = fitter if fitter is not None else default_fitter(model)
        self.store = store
        self.buffer = buffer if buffer is not None else CoverageBuffer()
        self.policy = policy if policy is not None else RecalPolicy()
        self.guard = guard if guard is not None else AcceptanceGuard()
        self.unit = unit
        self.holdout_every = int(holdout_every)
        self.recall_checks = max(1, int(recall_checks))
        self.synchronous = synchronous
        self._worker = FitWorker(self.fitter, synchronous)
        self.sphere = RunningSphere(coarse_every, coarse_min)
        self.stale = False
        self.n_fits = 0
        self._n_done = 0
        self._cal: Calibration | None = None
        self._support: np.ndarray | None = None      # (C,) cells the calibration was fitted on
        self._job: FitJob | None = None
        self.milestones = ev.Milestones()
        self.clock = MonotoneClock()
        self._frame_is_cal = False
        self._stage = Stage(stage, self.buffer.covariate_names)
        W = self.policy.window
        self.recaller = Recaller(W, remember, self.recall_checks, self.policy.drift_limit)
        self.tracker = DisturbanceTracker(disturbance, hold, len(self.buffer.covariate_names),
                                          W, unit)
        self._pending: list[Event] = []
        self.coarse_judge_coverage = float(coarse_judge_coverage)
        self._cal_ref: Reference | None = None
        self.environments = EnvironmentLog()
        self.status = StatusReporter()
        self.buffer.unframed = NO_ESTIMATE.format(n=self.sphere.every)
        if store is not None:
            self._load()

    # -- public -------------------------------------------------------------------------------
    @property
    def calibration(self) -> Calibration | None:
        """The calibration in use (None before the first is accepted or loaded)."""
        return self._cal

    @property
    def n_held(self) -> int:
        """Samples that disagreed with the reference so far: held back from the buffer against a
        calibration, only watched against the running sphere estimate before one."""
        return self.tracker.n_held

    @property
    def disturbance_rule(self) -> DisturbanceRule:
        return self.tracker.rule

    @property
    def coarse(self) -> tuple[np.ndarray, float] | None:
        """The running sphere estimate ``(centre (3,), radius)`` (sensor unit) or None."""
        return self.sphere.estimate

    @property
    def drift_limit(self) -> float | None:
        """Relative error (|calibrated field| / radius − 1) beyond which samples disagree with
        the calibration in use; None before one."""
        return self._cal_ref.limit if self._cal is not None and self._cal_ref is not None else None

    @property
    def nbytes(self) -> int:
        """Bytes held by the preallocated arrays (buffer, stage, drift, recall and hold-back
        windows, running sums): fixed whatever the samples ingested."""
        st = self._stage
        return (self.buffer.nbytes + self.policy.nbytes + self.recaller.nbytes
                + self.tracker.nbytes + st.m.nbytes + st.t.nbytes + st.cov.nbytes
                + self.sphere.nbytes)

    @property
    def coverage(self) -> CoverageReport:
        return self.buffer.report()

    @property
    def fit_in_flight(self) -> bool:
        """A fit is running (a finished one waiting for a disturbance's decision is not)."""
        return self._job is not None and not self._job.done

    def adopt_clock(self, other: "StreamingCalibrator") -> None:
        """Continue ``other``'s monotone clock (its shift after board restarts): a calibrator
        built to replace another (a daemon's reload) that takes over its buffer must stamp new
        samples on the clock the buffered ones carry."""
        self.clock.adopt(other.clock)

    @property
    def n_ingested(self) -> int:
        """Magnetometer samples taken so far (processed and staged)."""
        return self._n_done + self._stage.n_valid()

    def ingest(self, block) -> list:
        """Take a :class:`SampleBlock`; returns the events it caused (may be empty)."""
        n = len(block.t)
        stage = self._stage
        if n <= stage.capacity - stage.n:
            if stage.push(block, n):
                return self._drain_pending() + self._process(*stage.take())
            return self._drain_pending() if self._pending else []
        # Larger than the free room: what is staged and the whole block in one pass.
        return self._drain_pending() + self._process(*stage.take_with(block))

    def poll(self) -> list:
        """Process staged samples and pick up a finished fit; returns the events."""
        events = self._drain_pending()
        if self._stage.n:
            events += self._process(*self._stage.take())
        else:
            events += self._collect()
        return events

    def drain(self, timeout: float | None = None) -> list:
        """:meth:`poll`, then wait (up to ``timeout`` s) for the fit in flight and pick it up."""
        events = self.poll()
        job = self._job
        if job is not None and job.wait(timeout):
            events += self._collect()
        return events

    def apply(self, block, unit_vectors: bool = False) -> np.ndarray:
        """Calibrated samples of ``block`` (n,3): the field in the sensor unit (``|B| x``), or unit
        directions ``x`` with ``unit_vectors``. Uses the running sphere estimate before the first
        calibration; NaN rows where there is no magnetometer sample or no estimate yet."""
        return apply_block(block, self._cal, self.coarse, self.clock.shift, unit_vectors)

    def disagreement(self, block) -> np.ndarray:
        """Which samples of ``block`` disagree with the calibration in use (n,) bool: by the
        criterion that holds samples back (relative error beyond the drift limit on the
        directions it was fitted on, beyond :data:`~.disturbance.GROSS` anywhere). A stale
        calibration (after an environment change, still applied by :meth:`apply`) is judged
        the same way. All False before the first calibration and on rows without a
        magnetometer sample or whose covariates the calibration's effect terms lack. Pure: the
        quarantine, the drift window and the disturbance state are untouched, so it may be
        called on a block whether or not it has been processed yet."""
        ref = self._cal_ref if self._cal is not None else None
        return disagreement(block, ref, self._stage, self.clock.shift, self.buffer.cells,
                            self.buffer.covariate_names)

    def close(self, timeout: float | None = None) -> list:
        """Process what is staged and wait for a fit in flight; returns the last events. A
        disturbance still open is reported as undecided (``open``), and a fit that finished
        during it, waiting for its decision, is discarded."""
        events = self.drain(timeout)
        if self.tracker.open is not None:
            self.tracker.end(events, "open", self.clock.t_last)
            job = self._job
            if job is not None and job.done:
                self._job = None
                events.append(ev.discarded("disturbance_open", self.clock.t_last))
        return events + ([self.status.final(self, self.clock.t_last)] if self.n_ingested else [])

    # -- the per-stage path -------------------------------------------------------------------
    def _process(self, m, t, cov) -> list:
        n = len(m)
        if n == 0:
            return self._collect()
        events: list[Event] = []
        t = self.clock.stamp(t, events)
        self._n_done += n
        t_now = self.clock.t_last
        self.environments.begin(t[0])
        calibrated = self._cal is not None and not self.stale
        if calibrated:
            self._hold_back(m, t, cov, events)
        else:
            # The running sums serve only while no calibration is in force (a drift rebuilds
            # them from the buffer; the guard's reference radius then comes from the buffer).
            ref = self.sphere.reference
            if ref is not None:
                # The running sphere estimate only watches for an environment change: every
                # sample goes to the buffer (a sphere misfits an anisotropic sensor's extremes,
                # the samples a first fit needs most), but the disagreeing ones stay out of the
                # sums, so that the estimate does not drift into a mixture of two shells.
                held = self._disagreeing(m, t, cov, ref)[0]
                due = self.sphere.add(m[~held], counted=n)
            else:
                due = self.sphere.add(m)
            if due:         # the estimate frames directions until a calibration is in use
                self._update_coarse()
            stored, new_cells = self.buffer.insert(m, t, cov)
            if due and not self._frame_is_cal:
                self._update_unframed()
            self.policy.note(stored, new_cells, t_now)
            if ref is not None:
                self._check(ref, events)
            if self.recaller.remembered and self.stale:
                self._check_recall(m, t, events)
        if not self.buffer.unframed and self.milestones.passed(self.buffer.fraction):
            events.append(ev.coverage(self.buffer.report(), self.clock.t_last))
        events += self._collect()
        if self._job is None:
            request = self.policy.want_fit(
                calibrated=self._cal is not None and not self.stale,
                coverage=self.buffer.fraction, n_samples=self.buffer.n_samples,
                n_cells=self.buffer.cells.n_cells, capacity=self.buffer.capacity, t_now=t_now,
                plateau=self.policy.may_plateau(self._cal, not self.buffer.unframed))
            if request is not None:
                self.policy.requested(t_now)
                events += self._submit(request, t_now)
        return events + self.status.after(events, self, t_now)

    def _update_coarse(self) -> None:
        found, moved = self.sphere.refit()
        if found is None:
            return
        c, R = found
        if moved or self.stale and self._frame_is_cal:
            self._set_frame(c, np.eye(3) / R, from_cal=False)
        if self.tracker.open is None and not self._frame_is_cal \
                and self.buffer.fraction >= self.coarse_judge_coverage:
            # Before the first calibration, once the buffer covers enough of the sphere. A
            # sphere that no longer fits the stored samples (they begin to mix two shells)
            # does not replace the reference that may be about to see the change.
            ref = self.sphere.judge_reference(self.buffer.stored_mag(), self.buffer.occupied,
                                              self.policy.drift_limit)
            if ref is not None:
                if moved or self.sphere.reference is None:
                    self.policy.reset_window()
                self.sphere.reference = ref

    def _update_unframed(self) -> None:
        """Coverage is shown only while the running estimate is a sphere through the stored
        samples (:meth:`.running_sphere.RunningSphere.frame_problem`); the first time it is,
        the coverage reached is reported as a milestone."""
        was = self.buffer.unframed
        self.buffer.unframed = self.sphere.frame_problem(self.buffer.stored_mag())
        if was and not self.buffer.unframed:
            self.milestones.rebase(0.0)

    def _set_frame(self, center, A, from_cal: bool) -> None:
        self.buffer.set_frame(center, A)
        if from_cal:
            cal = self._cal
            R = cal.radius
            self._cal_ref = Reference(cal.b, np.asarray(A).T.copy(), R, float(cal.rms),
                                       self.policy.drift_limit(cal.rms, R), self._support,
                                       cal if cal.effects else None, True)
        self._frame_is_cal = from_cal
        if from_cal:
            self.buffer.unframed = ""
        self.milestones.rebase(self.buffer.fraction)

    def _hold_back(self, m, t, cov, events) -> None:
        """With a calibration in force: samples that disagree with it are held back (module
        :mod:`.disturbance`), the others go to the buffer; then the drift window is judged."""
        ref = self._cal_ref
        held, d, cell = self._disagreeing(m, t, cov, ref)
        if held.any():
            ok = ~held
            m, t, cov, d, cell = m[ok], t[ok], cov[ok], d[ok], cell[ok]
        if ref.cal is None and self._frame_is_cal:
            # The buffer's frame is the calibration's: one projection serves both.
            stored, new_cells = self.buffer.insert(m, t, cov, d=d, cell=cell)
        else:
            stored, new_cells = self.buffer.insert(m, t, cov)
        self.policy.note(stored, new_cells, self.clock.t_last)
        self._check(ref, events)

    def _disagreeing(self, m, t, cov, ref):
        """The tracker judges ``m`` (n,3) against ``ref``; the drift window observes the
        errors. Returns the disagreeing mask (n,), unit directions (n,3) and cells (n,)."""
        held, err, inside, d, cell = self.tracker.disagreeing(
            m, t, cov, ref, self.buffer.covariate_names, self.buffer.cells)
        self.policy.observe(err[inside], t[inside])
        return held, d, cell

    def _check(self, ref, events) -> None:
        check = self.policy.check(ref.rms, ref.radius)
        if check is None:
            return
        change = self.tracker.judge(check, ref, self.clock.t_last, events)
        if change is None:
            return
        in_force = change.held is not None
        self._close_environment(change.onset)
        self._forget(change.onset, events, "calibration in use is stale until a new one is "
                     "accepted or a remembered one fits again" if self._cal is not None else
                     "the samples of the old environment would bend the first fit", change.held)
        self.stale = self._cal is not None
        if in_force:        # the recall window watches the new field from here on
            self.recaller.restart()
        if self._job is not None:
            self._job.obsolete = True

    def _close_environment(self, end: float) -> None:
        self.environments.close(end, self.buffer.measured_fraction, self.buffer.n_samples)

    def environment_summary(self) -> list:
        """The environments seen (:meth:`.environments.EnvironmentLog.summary`)."""
        return self.environments.summary(self.buffer.measured_fraction, self.buffer.n_samples,
                                         self._cal is not None and not self.stale)

    def _forget(self, onset: float, events, why: str, held=None) -> None:
        """Drop the buffer's samples older than ``onset``; ``held`` (m, t, cov): samples held back
        since then, which belong to the new environment and join the buffer."""
        dropped = self.buffer.forget_before(onset)
        n_held = 0
        if held is not None and len(held[1]):
            n_held = len(held[1])
            self.buffer.insert(*held)
        kept = self.buffer.snapshot()
        self.sphere.reset(kept.m)
        if not self._frame_is_cal:
            self.buffer.unframed = NO_ESTIMATE.format(n=self.sphere.every)
        self.policy.restart()
        self.milestones.rebase(self.buffer.fraction)
        events.append(ev.forgot(dropped, len(kept), n_held, onset, why, self.clock.t_last))

    def _check_recall(self, m, t, events) -> None:
        """While stale: a remembered calibration that fits the new samples ``m`` (n,3) at ``t``
        (n,) s again (module :mod:`.recall`) is back in use."""
        found = self.recaller.observe(m, t)
        if found is None:
            return
        cal, start = found.calibration, found.start
        self._cal, self._support, self.stale = cal, found.support, False
        if self._job is not None:
            self._job.obsolete = True
        events.append(ev.recalled(found, self.clock.t_last))
        self._close_environment(start)
        self.environments.calibrated = True
        self.tracker.clear()            # what it was judged against is gone
        self._forget(start, events, "samples of the other environment")
        self.policy.last_request_t = self.clock.t_last   # coverage decides the next fit, as a refit
        self._set_frame(cal.b, np.linalg.inv(cal.K), from_cal=True)
        self._save(cal, events)

    # -- fitting ------------------------------------------------------------------------------
    def _submit(self, request, t_now) -> list:
        snap = self.buffer.snapshot()
        held = (np.arange(len(snap)) + self.n_fits) % self.holdout_every == 0
        job = FitJob(snap.subset(~held), snap.subset(held), self.buffer.measured_fraction, t_now,
                   self.buffer.occupied)
        self.n_fits += 1
        self._job = job
        event = ev.fit_started(self.n_fits, request, job, t_now)
        self._worker.submit(job)
        if self._worker.synchronous:
            return [event] + self._collect()
        return [event]

    def _collect(self) -> list:
        job = self._job
        if job is None or not job.done:
            return []
        dist = self.tracker.open
        if dist is not None and dist.hold and not job.obsolete and job.error is None:
            # Its held-out samples are all from before the disturbance: it waits for the
            # decision (transient: judged then; environment change: obsolete) — but not for
            # good: the drift window only fills with samples in directions the calibration was
            # fitted on, and a board that stays elsewhere would block every later fit.
            if self.tracker.waits(self.clock.t_last):
                return []
            events = []
            self.tracker.end(events, "undecided", self.clock.t_last)
            return events + self._collect()
        self._job = None
        t = self.clock.t_last
        if job.obsolete:
            return [ev.discarded("environment_changed", t)]
        if job.error is not None:
            return [ev.fit_failed(job.error, t)]
        cand = job.result.replace(unit=self.unit, coverage=job.result.coverage
                                  if job.coverage is None else round(float(job.coverage), 4))
        if self.coarse is None or self._frame_is_cal:
            # the guard's reference radius, on demand
            found = sphere_of_samples(self.buffer.stored_mag(), self.sphere.min_n)
            if found is not None:
                self.sphere.estimate = found
        current = self._cal if self._cal is not None else self.sphere.calibration(self.unit)
        ref_R = self.coarse[1] if self.coarse is not None else None
        decision = self.guard.check(cand, job.holdout.m, job.holdout.columns(), current, ref_R)
        if not decision.accepted:
            return [ev.judged(cand, decision, self.unit, t)]
        events = []
        self.tracker.end(events, "reference_replaced", t)     # the running estimate's
        self._cal = cand
        self._support = job.support
        self.recaller.remember(cand, job.support)
        self.stale = False
        self.environments.calibrated = True
        self.policy.reset_window()
        self._set_frame(cand.b, np.linalg.inv(cand.K), from_cal=True)
        events.append(ev.judged(cand, decision, self.unit, t))
        self._save(cand, events)
        return events

    def _save(self, cal, events) -> None:
        if self.store is None:
            return
        t = self.clock.t_last
        try:
            path = self.store.save(cal)
            events.append(Event("stored", f"saved {self.store.current_path} ({path.name})",
                                {"path": str(self.store.current_path)}, t))
        except Exception as exc:    # keep calibrating; the old file stays valid
            events.append(Event("store_error", f"could not save the calibration: {exc}", {}, t))

    def _load(self) -> None:
        result = self.store.load()
        self._pending += ev.loaded(result)
        if result.calibration is not None:
            self._cal = result.calibration
            self.recaller.remember(self._cal, None)     # fitted on directions unknown: all
            self._set_frame(self._cal.b, np.linalg.inv(self._cal.K), from_cal=True)

    def _drain_pending(self) -> list:
        out, self._pending = self._pending, []
        return out
