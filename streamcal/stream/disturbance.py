"""Transient disturbances versus environment changes: held-back samples and the new-shell test.

A phone or a tool passing the board adds a field that rises and falls within seconds; a magnet
stuck to the board (a new hard iron) adds a constant offset ``δ`` for good. Both make the field
disagree with the calibration in use, ``y = K⁻¹(m − b)`` no longer on the unit sphere. Only the
second should make the calibrator forget its buffer. Two observations tell them apart:

- a new hard iron moves the shell, it does not deform it: every disagreeing sample is on the unit
  sphere around one new centre ``c = K⁻¹δ``. A phone's field changes with its distance, so the
  samples it disturbs trace a curve through the shell (out and back, 1/r³), on no unit sphere;
- a phone leaves: the samples agree again after a few seconds.

So disagreeing samples (relative error ``|‖y‖ − 1|`` above the drift limit, on directions the
calibration was fitted on; above :data:`GROSS` anywhere) are *held back* in a bounded
:class:`Quarantine` instead of entering the coverage buffer or the running sums. When a good part
of the drift window disagrees, a *disturbance* is open from its first disagreeing sample on.
(A phone's field can also carry a reading across the shell, where that sample looks clean and
enters the buffer: a handful per pass, which the robust fit tolerates.) The held samples that
disagree are fitted with a unit sphere of free centre (:func:`shell_fit`; the field strength
does not change with hard iron). The disturbance is an environment change when most of the
window disagrees (its median is beyond the limit, as before) and, at least ``min_age_s`` after
it began, the held samples lie on the new shell as well as clean samples lie on the
calibration's (median residual within the drift limit), or when it lasts ``persist_s``. It is a
transient when the window agrees again first. The held samples then either join the buffer
(they are the new environment's first samples) or are dropped.

The unit-radius fit is Gauss–Newton on ``r_i = ‖y_i − c‖ − 1``, ``∂r_i/∂c = −u_i`` with
``u_i = (y_i − c)/‖y_i − c‖``, from ``c = 0`` (the calibration in use), with a small Levenberg
damping: samples of one direction (a board at rest) fix ``c`` along that direction only, and the
damped step takes the smallest offset that explains them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Relative error (fraction of the field) beyond which a sample is held back on any direction,
#: even where the calibration extrapolates (a calibration fitted on part of the sphere may be off
#: by ~10 % elsewhere; a phone at 5 cm adds several times the Earth field).
GROSS = 0.5
_SHELL_ITER, _SHELL_DAMPING = 12, 1e-3


def shell_fit(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``c`` (3,) of the unit sphere nearest to points ``y`` (n,3) (calibrated units) and
    the residuals ``|‖y − c‖ − 1|`` (n,)."""
    c = np.zeros(3)
    n = len(y)
    for _ in range(_SHELL_ITER):
        v = y - c
        dist = np.sqrt(np.einsum("nk,nk->n", v, v))
        u = v / np.maximum(dist, 1e-12)[:, None]
        r = dist - 1.0
        step = np.linalg.solve(u.T @ u + _SHELL_DAMPING * n * np.eye(3), u.T @ r)
        c = c + step
        if step @ step < 1e-16:
            break
    v = y - c
    return c, np.abs(np.sqrt(np.einsum("nk,nk->n", v, v)) - 1.0)


class Quarantine:
    """Bounded ring of held-back samples: ``m`` (Q,3) sensor unit, ``y`` (Q,3) calibrated,
    ``t`` (Q,) s, covariates (Q,P); the oldest are overwritten. ``n_held`` counts every sample
    ever pushed: held back from the buffer against a calibration, or only watched (kept in the
    buffer too) against the running sphere estimate before one."""

    def __init__(self, capacity: int = 2048, n_covariates: int = 0):
        Q = max(1, int(capacity))
        self.m = np.empty((Q, 3))
        self.y = np.empty((Q, 3))
        self.t = np.full(Q, -np.inf)
        self.cov = np.empty((Q, n_covariates))
        self._n = 0
        self.n_held = 0

    @property
    def capacity(self) -> int:
        return len(self.t)

    def push(self, m, y, t, cov) -> None:
        Q = self.capacity
        k = len(t)
        self.n_held += k
        m, y, t, cov = m[-Q:], y[-Q:], t[-Q:], cov[-Q:]
        pos = (self._n + np.arange(len(t))) % Q
        self.m[pos], self.y[pos], self.t[pos], self.cov[pos] = m, y, t, cov
        self._n += len(t)

    def since(self, t0: float) -> np.ndarray:
        """Ring positions of the held samples at ``t ≥ t0``, oldest first."""
        idx = np.flatnonzero(self.t >= t0)
        return idx[np.argsort(self.t[idx], kind="stable")]

    def clear(self) -> None:
        self.t[:] = -np.inf
        self._n = 0


@dataclass
class Disturbance:
    """An open disagreement with the calibration in use: ``start`` (s, first sample beyond the
    limit), ``peak`` (largest relative error of a held sample) at ``peak_t`` (s), ``n_held``
    samples held back since it began, and the last new-shell residual ``shell`` (relative,
    median); ``radius`` of the reference (sensor unit);
    ``hold``: the samples were held back (against a calibration) or only watched."""

    start: float
    peak: float = 0.0
    peak_t: float = float("nan")
    n_held: int = 0
    shell: float = float("nan")
    radius: float = 1.0
    hold: bool = True

    def note(self, err: np.ndarray, t: np.ndarray) -> None:
        """Count held samples (relative errors ``err`` (n,) at times ``t``)."""
        self.n_held += len(err)
        if len(err):
            k = int(np.argmax(err))
            if err[k] > self.peak:
                self.peak, self.peak_t = float(err[k]), float(t[k])


@dataclass(frozen=True)
class DisturbanceRule:
    """When an open disturbance ends or becomes an environment change.

    Args:
        min_age_s: least age (s) of a disturbance before the new-shell test is believed. Over
            its first second a phone's rising field can pass for an arc of a shifted shell (seen
            in simulated passes: median shell residual 0.5× the limit after 1.3 s); a phone
            passing by has turned around within 3 s of the window noticing it, and samples
            of its rise and fall lie on no one shell.
        min_held: held samples needed before the new-shell test is believed (at least 4: a
            unit sphere of free centre fits any 3 points).
        shell_k: the held samples fit one unit sphere when their median residual is at most
            ``shell_k`` × the drift limit (the same yardstick as the calibration's own fit).
        persist_s: a disagreement lasting this long is an environment change whatever its shape
            (a phone left on the table next to the board is one, until it is taken away — then
            the remembered calibration is recalled).
        open_fraction: a disturbance opens when more than this fraction of the drift window
            disagrees (a correct calibration has hardly any sample beyond the limit; a phone
            passing in two seconds may disturb fewer than half of a 200-sample window);
        calm_fraction: …and ends when at most this fraction disagrees (hysteresis).

    An environment change needs, besides the shell or the duration, the drift window's median
    beyond the limit (most of the field disagrees).
    """

    min_age_s: float = 3.0
    min_held: int = 100
    shell_k: float = 1.0
    persist_s: float = 20.0
    open_fraction: float = 0.25
    calm_fraction: float = 0.1

    def new_shell(self, dist: Disturbance, y: np.ndarray, limit: float,
                  t_now: float) -> tuple[bool, np.ndarray | None, float]:
        """Fit the held samples ``y`` (n,3) that disagree with the calibration in use (relative
        error beyond ``limit``) with one unit sphere. Returns ``(ok, center, shell)``: ``ok``
        when they lie on it and the disturbance is old enough (``t_now`` s); the sphere's
        centre (3,) (calibrated units) and median residual (relative), or ``(False, None,
        dist.shell)`` when there are too few samples or it is too early to fit."""
        y = y[np.abs(np.sqrt(np.einsum("nk,nk->n", y, y)) - 1.0) > limit]
        # A unit sphere of free centre needs 3 samples; fewer than 4 fit any centre exactly.
        if len(y) < max(self.min_held, 4) or t_now - dist.start < self.min_age_s:
            return False, None, dist.shell
        center, res = shell_fit(y)
        shell = float(np.median(res))
        return shell <= self.shell_k * limit, center, shell
