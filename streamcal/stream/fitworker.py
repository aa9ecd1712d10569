"""Fits off the ingest path: one at a time on a worker thread, or inline for a replay.

A :class:`FitJob` is the snapshot a fit runs on (fit set, held-out samples, coverage, time,
the cells it covers) and its :class:`concurrent.futures.Future`. :class:`FitWorker` runs jobs on a
single-worker :class:`~concurrent.futures.ThreadPoolExecutor` (a live service: ingest never waits
for a fit), or on :class:`SynchronousExecutor` (a replay: the fit runs when it is due, so the
output does not depend on how fast the fit runs).
"""
from __future__ import annotations

import concurrent.futures as cf

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration
from .coverage import Snapshot


class SynchronousExecutor(cf.Executor):
    """An executor that runs each call at once, in the caller's thread; its future is done on
    return (an exception, even a BaseException, is kept in the future, as a thread's would)."""

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        future: cf.Future = cf.Future()
        future.set_running_or_notify_cancel()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:        # reported as a fit_failed event, never lost
            future.set_exception(exc)
        return future


class FitJob:
    """One fit: ``fit_set`` and ``holdout`` snapshots, the buffer's ``coverage`` (0..1) and
    sample time ``t`` (s) when it started, ``support`` (C,) bool the occupied cells; ``obsolete``
    once the environment changed while it ran."""

    def __init__(self, fit_set: Snapshot, holdout: Snapshot, coverage: float, t: float,
                 support: np.ndarray):
        self.fit_set, self.holdout, self.coverage, self.t = fit_set, holdout, coverage, t
        self.support = support
        self.obsolete = False
        self.future: cf.Future | None = None

    @property
    def done(self) -> bool:
        return self.future is not None and self.future.done()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait up to ``timeout`` s (None: for ever) for the fit; True when it is done."""
        if self.future is None:
            return False
        cf.wait([self.future], timeout)
        return self.future.done()

    @property
    def error(self) -> BaseException | None:
        return self.future.exception() if self.done else None

    @property
    def result(self):
        """The fitted :class:`~streamcal.calibration.Calibration` (None until done or on error)."""
        return self.future.result() if self.done and self.error is None else None


class FitWorker:
    """Runs ``fitter(fit_set) -> Calibration`` for jobs, at most one at a time.

    Args:
        fitter: the fit.
        synchronous: run each fit inline (:class:`SynchronousExecutor`) instead of on the
            single worker thread.
    """

    def __init__(self, fitter, synchronous: bool = False):
        self.fitter = fitter
        self.synchronous = bool(synchronous)
        self._executor: cf.Executor | None = SynchronousExecutor() if synchronous else None

    def submit(self, job: FitJob) -> FitJob:
        if self._executor is None:      # the thread starts with the first fit
            self._executor = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="streamcal-fit")
        job.future = self._executor.submit(self.fitter, job.fit_set)
        return job

    def shutdown(self) -> None:
        """Let the worker thread end once the fit in flight (if any) is done; no wait."""
        if self._executor is not None:
            self._executor.shutdown(wait=False)
            self._executor = None


#: The model a fit falls back to when the directions leave the one asked for undetermined.
HARD_IRON_ONLY = ("hard_iron",)


def default_fitter(model=DEFAULT_MODEL, kernel: str = "cauchy"):
    """``fitter(snapshot) -> Calibration`` running :func:`streamcal.fitting.fit` on the stored
    samples (with their covariates when the model has effects beyond K and b); when the samples
    leave that model undetermined, the hard iron alone (:data:`HARD_IRON_ONLY`, its
    ``model`` says so), or the first error when that fails too."""

    def fit_snapshot(snap: Snapshot) -> Calibration:
        from ..errors import InsufficientDataError
        from ..fitting import fit

        try:
            if set(model) <= {"hard_iron", "soft_iron", "scale"}:
                return fit(snap.m, model=tuple(model), kernel=kernel)
            return fit(snap.to_track(), model=tuple(model), kernel=kernel)
        except InsufficientDataError as exc:
            if tuple(model) == HARD_IRON_ONLY:
                raise
            # A cap or band of directions that leaves the soft iron undetermined may still fix
            # the centre: the hard iron alone, which the guard judges like any candidate.
            try:
                return fit(snap.m, model=HARD_IRON_ONLY, kernel=kernel)
            except InsufficientDataError:
                raise exc from None

    return fit_snapshot
