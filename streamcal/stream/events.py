"""What the streaming calibrator reports: :class:`Event`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..units import with_unit


@dataclass(frozen=True)
class Event:
    """Something the calibrator did or noticed.

    ``kind``: ``loaded``, ``load_problem``, ``coverage``, ``fit_started``, ``fit_failed``,
    ``accepted``, ``rejected``, ``discarded``, ``disturbance`` (a disagreement ended:
    ``outcome`` ``transient``, or undecided: ``reference_replaced``, ``undecided`` (not
    judgeable within the persistence time while a finished fit waited), ``open`` at the end of
    the stream; ``start``, ``end``, ``peak`` error in the sensor unit, ``held`` samples held back),
    ``drift`` (an environment change), ``forgot``, ``recalled``, ``clock_reset`` (sample times
    went back; later ones are shifted by ``shift`` s), ``stored``, ``store_error``. ``t`` is
    the sample time (s) at which it happened, ``data`` its figures
    (JSON-ready); ``detail`` an object behind them, not serialized (a ``coverage`` event's
    :class:`~.coverage.CoverageReport`, with the occupied cells, for a map that agrees with it).
    """

    kind: str
    message: str
    data: dict = field(default_factory=dict)
    t: float | None = None
    detail: object = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        return {"event": self.kind, "t": self.t, "message": self.message, **self.data}


# -- the calibrator's events, worded once -----------------------------------------------------
def forgot(dropped: int, kept: int, n_held: int, onset: float, why: str, t: float) -> Event:
    """The buffer forgot ``dropped`` samples older than ``onset`` (s), kept ``kept`` (with
    ``n_held`` held-back samples of the new field)."""
    return Event("forgot", f"forgot {dropped} stored samples older than t={onset:.2f} s; kept "
                 f"{kept}" + (f" (with {n_held} held-back samples of the new field)"
                              if n_held else "") + f"; {why}",
                 {"dropped": dropped, "kept": kept, "onset": onset, "held_added": n_held}, t)


def recalled(found, t: float) -> Event:
    """A remembered calibration is back (``found``: a :class:`~.recall.Recall`)."""
    cal = found.calibration
    return Event("recalled", f"the field fits a remembered calibration again (median relative "
                 f"error {found.stat:.3f} ≤ {found.limit:.3f} since t={found.start:.2f} s): "
                 f"back in use, b = {np.round(cal.b, 2).tolist()}",
                 {"value": found.stat, "limit": found.limit, "onset": found.start,
                  "K": cal.K.round(6).tolist(), "b": cal.b.round(6).tolist()}, t)


def fit_started(number: int, request, job, t: float) -> Event:
    """Fit ``number`` started for ``request`` (a :class:`~.policy.FitRequest`) on ``job``."""
    coverage = ("coverage not measured (the buffer's cells filled about a running sphere that "
                "the samples do not fit)" if job.coverage is None
                else f"coverage {100 * job.coverage:.0f}%")
    return Event("fit_started", f"fit #{number} started ({request.reason}): {len(job.fit_set)} "
                 f"samples, {len(job.holdout)} held out, {coverage}",
                 {"reason": request.reason, "fit": number, "n_fit": len(job.fit_set),
                  "n_holdout": len(job.holdout), **request.data,
                  "coverage": None if job.coverage is None else round(job.coverage, 4)}, t)


def verdict(cand, decision, unit: str, t: float) -> Event:
    """The guard's ``decision`` (a :class:`~.guard.Decision`) on the candidate ``cand``."""
    rms = float(cand.rms)
    data = {**decision.to_dict(), "K": cand.K.round(6).tolist(), "b": cand.b.round(6).tolist(),
            "rms": rms if np.isfinite(rms) else None, "coverage_at_fit": cand.coverage}
    if not decision.accepted:
        return Event("rejected", f"candidate rejected: {decision.text()}", data, t)
    return Event("accepted", f"calibration accepted ({decision.text()}): rms "
                 f"{with_unit(f'{cand.rms:.3g}', unit)}, b = {np.round(cand.b, 2).tolist()}",
                 data, t)


def coverage(report, t: float) -> Event:
    """A coverage milestone (``report``: a :class:`~.coverage.CoverageReport`)."""
    return Event("coverage", report.text(), report.to_dict(), t, report)


def loaded(result) -> list:
    """What loading the state directory found (``result``: a :class:`~.store.LoadResult`):
    ``load_problem`` per rejected file (a missing current file only when it fell back) and
    ``loaded``."""
    out = [Event("load_problem", problem, {}) for problem in result.problems
           if not problem.endswith(": missing") or result.fell_back]
    if result.calibration is not None:
        how = " (fallback: the current file was missing or damaged)" if result.fell_back else ""
        out.append(Event("loaded", f"calibration in use loaded from {result.path}{how}",
                         {"path": str(result.path), "fell_back": result.fell_back}))
    return out


#: Why a finished fit's result was discarded, in words.
DISCARDED = {"environment_changed": "the environment changed while it ran",
             "disturbance_open": "it finished during a disturbance still undecided when the "
                                 "stream ended"}


def discarded(reason: str, t: float) -> Event:
    """A finished fit's result was discarded for ``reason`` (a key of :data:`DISCARDED`)."""
    return Event("discarded", f"fit result discarded: {DISCARDED[reason]}", {"reason": reason}, t)


def fit_failed(error: BaseException, t: float) -> Event:
    return Event("fit_failed", f"fit failed: {error}", {"error": type(error).__name__}, t)


class Milestones:
    """Coverage milestones (fractions of the sphere, :data:`STEPS`) reported once each as the
    coverage grows; after the buffer forgot or changed frame, from where the coverage is then."""

    STEPS = (0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9, 0.95)

    def __init__(self):
        self.reached = 0.0

    def floor(self, fraction: float) -> float:
        """The highest milestone at or below ``fraction`` (0 below the first)."""
        passed = [m for m in self.STEPS if fraction >= m]
        return passed[-1] if passed else 0.0

    def rebase(self, fraction: float) -> None:
        self.reached = self.floor(fraction)

    def passed(self, fraction: float) -> bool:
        """True when ``fraction`` passed a milestone above the last reported one (it is then
        the last reported)."""
        now = self.floor(fraction)
        if now > self.reached:
            self.reached = now
            return True
        return False
