"""The disturbance tracker: held-back samples, open disturbances and the environment-change call.

One :class:`DisturbanceTracker` per calibrator. It is given, per stage, the samples judged
against a :class:`~.reference.Reference` (the calibration in force, or the running sphere
estimate before one) and, per drift-window check (:class:`~.policy.WindowCheck`), decides
whether a disturbance opens, ends (a transient) or is an environment change (module
:mod:`.disturbance` says how). It only reports: the calibrator, told of a change by the
:class:`Change` :meth:`DisturbanceTracker.judge` returns, forgets its buffer and marks its
calibration stale.

Samples that disagree with
the calibration in force are held back from the buffer and the fits. A passing phone is a
transient: when the field agrees again, one ``disturbance`` event reports it and the buffer is
untouched. When the disagreement persists on one shifted shell (a new hard iron), or lasts
``DisturbanceRule.persist_s`` whatever its shape (``drift``), the buffer forgets the samples taken
before the change began, the held ones join it, the calibration in use is marked stale (it is
kept and applied: a stale calibration is better than none) and the next fit is a first one.
Before the first calibration the running sphere estimate, once it fits the stored samples,
watches the same way, so that a first fit is not bent by two environments. The last
``remember`` accepted calibrations are remembered (with the cells they were fitted on): while
stale, a full window of new samples that fits one of them again (the magnet was removed, the
board is back in its old place) brings it back at once (``recalled``), without waiting for the
coverage a refit needs. A candidate always has to beat the calibration in use on held-out
samples, so a worse calibration is never accepted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..units import with_unit
from .disturbance import Disturbance, DisturbanceRule, Quarantine
from .events import Event
from .reference import Reference, beyond


@dataclass(frozen=True)
class Change:
    """An environment change: it began at ``onset`` (s); ``why`` in words; ``held`` the samples
    ``(m (n,3), t (n,), cov (n,P))`` held back since then (they belong to the new environment),
    or None when the reference only watched (the running sphere estimate)."""

    onset: float
    why: str
    held: tuple | None


class DisturbanceTracker:
    """Samples that disagree with the reference, and what their disagreement means.

    Args:
        rule: the :class:`~.disturbance.DisturbanceRule`.
        hold: capacity (samples) of the ring of held-back samples.
        n_covariates: covariate columns per sample (the buffer's).
        window: samples in the drift window (the policy's): their projections are kept to test
            whether a calm window still fits a shifted shell.
        unit: sensor unit (event messages).
    """

    def __init__(self, rule: DisturbanceRule | None = None, hold: int = 2048,
                 n_covariates: int = 0, window: int = 200, unit: str = "uT"):
        self.rule = rule if rule is not None else DisturbanceRule()
        self.unit = unit
        self.quarantine = Quarantine(hold, n_covariates)
        self.open: Disturbance | None = None
        self._window_y = np.zeros((int(window), 3))
        self._window_n = 0

    @property
    def n_held(self) -> int:
        """Samples that disagreed with the reference so far."""
        return self.quarantine.n_held

    @property
    def nbytes(self) -> int:
        """Bytes of the preallocated rings (fixed)."""
        q = self.quarantine
        return q.m.nbytes + q.y.nbytes + q.t.nbytes + q.cov.nbytes + self._window_y.nbytes

    def disagreeing(self, m, t, cov, ref: Reference, names, cells):
        """Judge samples ``m`` (n,3) at ``t`` (n,) s with covariates ``cov`` (n,P) named
        ``names`` against ``ref`` (``cells``: the buffer's partition). The disagreeing ones are
        recorded. Returns ``(held (n,), err (n,), inside (n,), d (n,3), cell (n,))`` as
        :func:`.reference.beyond`; the caller's drift window observes ``err[inside]``."""
        y = ref.project(m, t, cov, names)
        held, err, inside, d, cell = beyond(y, ref, cells)
        yi = y[inside][-len(self._window_y):]
        W = len(self._window_y)
        self._window_y[(self._window_n + np.arange(len(yi))) % W] = yi
        self._window_n += len(yi)
        if held.any():
            self.quarantine.push(m[held], y[held], t[held], cov[held])
            if self.open is not None:
                self.open.note(err[held], t[held])
        return held, err, inside, d, cell

    def clear(self) -> None:
        """Forget the open disturbance and the held samples (what they were judged against is
        gone)."""
        self.open = None
        self.quarantine.clear()

    def waits(self, t_now: float) -> bool:
        """A finished fit must wait: a disturbance holding samples back is open since less than
        ``persist_s`` before ``t_now`` (s)."""
        d = self.open
        return d is not None and d.hold and t_now - d.start < self.rule.persist_s

    def judge(self, check, ref: Reference, t_now: float, events: list) -> Change | None:
        """Open, close or confirm a disturbance from one drift-window ``check``
        (:class:`~.policy.WindowCheck`) against ``ref`` at ``t_now`` (s); appends the events.
        Returns the :class:`Change` when the environment changed (the tracker is then clear)."""
        dist, rule, q = self.open, self.rule, self.quarantine
        if dist is None:
            if check.fraction <= rule.open_fraction:
                return None
            dist = self.open = Disturbance(check.onset, radius=ref.radius, hold=ref.hold)
            early = q.since(check.onset)        # held before the window turned: count them
            dist.note(np.abs(np.linalg.norm(q.y[early], axis=1) - 1.0), q.t[early])
        elif check.fraction <= rule.calm_fraction:
            if not self._shift_persists(dist, check.limit, t_now):
                self.end(events, "transient", t_now)
                return None
        # An environment change needs most of the window to disagree (its median beyond the
        # limit) and the new shell or the duration; against a calibration, whose acceptances
        # wait for the decision, the duration alone: a change of one or two drift limits moves
        # the median little but keeps a disturbance open for good.
        age = t_now - dist.start
        if not (check.disagrees or dist.hold and age >= rule.persist_s):
            return None
        idx = q.since(dist.start)
        ok, center, shell = rule.new_shell(dist, q.y[idx], check.limit, t_now)
        dist.shell = shell
        if ok and check.disagrees:
            why = (f"the disagreeing samples lie on one shell (median residual {shell:.3f} "
                   f"≤ {rule.shell_k * check.limit:.3f}): a new hard iron?")
            reason = "new_shell"
        elif age >= rule.persist_s:
            why = (f"the disagreement lasted {age:.1f} s ≥ {rule.persist_s:g} s"
                   + ("" if check.disagrees else f" ({100 * check.fraction:.0f}% of the "
                      f"window beyond the limit)"))
            reason = "persisted"
        else:
            return None
        # The new shell's centre in the sensor unit: how far the hard iron moved (m − b = K y).
        shift = np.linalg.solve(ref.AT.T, center) if ok else None
        in_force = ref.hold
        what = ("field no longer fits the calibration" if in_force else
                "field left the running sphere estimate (no calibration in force)")
        moved = ("" if shift is None else
                 f"; the shell's centre moved by "
                 f"{with_unit(str(np.round(shift, 2).tolist()), self.unit)} "
                 "(the hard-iron change, if the soft iron is unchanged)")
        events.append(Event("drift", f"{what}: median relative error {check.stat:.3f} "
                            f"{'>' if check.disagrees else '≤'} {check.limit:.3f} since "
                            f"t={dist.start:.2f} s; {why}{moved}",
                            {"value": check.stat, "limit": check.limit, "onset": dist.start,
                             "reason": reason, "shell_residual": _finite(dist.shell),
                             "hard_iron_shift": None if shift is None else
                             np.round(shift, 6).tolist(),
                             "held": dist.n_held, "calibrated": in_force}, t_now))
        held = (q.m[idx].copy(), q.t[idx].copy(), q.cov[idx].copy()) if in_force else None
        self.clear()
        return Change(dist.start, why, held)

    def end(self, events: list, outcome: str, t_now: float) -> None:
        """Report the open disturbance (if any) at ``t_now`` (s) and drop its held samples.
        ``outcome``: ``transient`` (the field agrees again), ``reference_replaced`` (a first
        calibration replaced the running estimate it was judged against: undecided),
        ``undecided`` (too few samples in the calibration's directions to judge it within the
        persistence time, while a finished fit waited) or ``open`` (the stream ended)."""
        dist, self.open = self.open, None
        if dist is None:
            return
        R, end = dist.radius, t_now
        what = {"transient": f"transient disturbance from t={dist.start:.2f} to {end:.2f} s",
                "reference_replaced": f"disturbance from t={dist.start:.2f} to {end:.2f} s "
                f"left undecided: the running estimate it was judged against was replaced by "
                f"the accepted calibration",
                "open": f"disturbance since t={dist.start:.2f} s still open (undecided) when "
                f"the stream ended at t={end:.2f} s",
                "undecided": f"disturbance from t={dist.start:.2f} to {end:.2f} s left "
                f"undecided: too few samples in the directions the calibration covers to judge "
                f"it within {self.rule.persist_s:g} s"}[outcome]
        events.append(Event(
            "disturbance", f"{what}: peak error {with_unit(f'{dist.peak * R:.3g}', self.unit)} "
            f"({100 * dist.peak:.0f}% of the field) at t={dist.peak_t:.2f} s; {dist.n_held} "
            "samples " + ("held back" + (", buffer kept" if outcome == "transient" else "")
                          if dist.hold else "disagreed with the running estimate"),
            {"start": dist.start, "end": end, "duration": end - dist.start,
             "peak": dist.peak * R, "peak_relative": dist.peak, "peak_t": dist.peak_t,
             "held": dist.n_held if dist.hold else 0, "disagreeing": dist.n_held,
             "shell_residual": _finite(dist.shell), "outcome": outcome,
             "open": outcome == "open"}, end))
        self.quarantine.clear()

    def _shift_persists(self, dist, limit: float, t_now: float) -> bool:
        """A calm window is no end when the held samples lie on one shifted shell and the
        window's samples fit that shell too: a small new hard iron (one or two drift limits)
        leaves the field within the limit on the directions across the shift."""
        if not dist.hold:
            return False
        q = self.quarantine
        ok, center, _ = self.rule.new_shell(dist, q.y[q.since(dist.start)], limit, t_now)
        if not ok:
            return False
        v = self._window_y - center
        err = np.abs(np.sqrt(np.einsum("nk,nk->n", v, v)) - 1.0)
        return float(np.mean(err > limit)) <= self.rule.calm_fraction


def _finite(v):
    v = float(v)
    return v if np.isfinite(v) else None
