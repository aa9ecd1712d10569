"""Gyro samples → the board's rotation: the readings of a track, the magnetometer rows that are
fresh, the gyro rows that are saturated, pairs of samples a horizon apart, and the orientation
integrated from the rates (:class:`Orientation`). Shared by the gyro-tied lag fit
(:mod:`.gyro_lag`) and the gyro link of a held calibration (:mod:`.gyro_link`)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InsufficientDataError, MissingColumnsError
from ..quaternion import cumulative_rotation, qmul

#: A gyro full-scale value reached on this many rows marks saturation (pairs across it dropped).
SATURATED_ROWS = 3


def gyro_rates(track) -> tuple[np.ndarray, np.ndarray]:
    """IMU instants (G,) s, strictly increasing, and the gyro readings there (G,3) rad/s."""
    if not track.has("gyro"):
        raise MissingColumnsError("the gyro-tied lag needs gyroscope columns (gx, gy, gz), "
                                  "which the track lacks")
    t = np.asarray(track.t[track.gyro_rows], dtype=float)
    w = np.asarray(track.gyro, dtype=float)
    keep = np.r_[True, np.diff(t) > 0]
    if keep.sum() < 10:
        raise InsufficientDataError(f"{int(keep.sum())} gyro samples are too few for the "
                                    "gyro-tied lag")
    return t[keep], w[keep]


def fresh(m: np.ndarray) -> np.ndarray:
    """(N,) False for a magnetometer reading (N,3) identical on all three axes to the one
    before: a sample-and-hold repeat logged faster than the sensor updates. Its stamp is later
    than its sampling instant, which would read as lag, so the pairs leave repeats out."""
    out = np.ones(len(m), bool)
    out[1:] = ~np.all(m[1:] == m[:-1], axis=1)
    return out


def saturated(w: np.ndarray) -> np.ndarray:
    """(G,) True where a gyro reading (G,3) rad/s sits at the full-scale value: an axis exactly
    at the largest |ω| of the track, that value read on at least :data:`SATURATED_ROWS` rows
    (a clipped rate says nothing of the rotation; a smooth peak is not repeated exactly)."""
    top = float(np.max(np.abs(w))) if len(w) else 0.0
    at = np.abs(w) == top
    return at.any(axis=1) if top > 0 and at.sum() >= SATURATED_ROWS else np.zeros(len(w), bool)


def horizon_pairs(t: np.ndarray, horizon: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices (a, b), each (P,): for every sample a of the stamps ``t`` (N,) s, b the
    first sample at least ``horizon`` s after it (the next one when that is later; irregular
    sampling allowed). The last samples, with no such b, have no pair."""
    n = len(t)
    a = np.arange(n)
    b = np.maximum(np.searchsorted(t, t + horizon), a + 1)
    return a[b < n], b[b < n]


def clear_of_saturation(t_g: np.ndarray, w: np.ndarray, t_from: np.ndarray,
                        t_to: np.ndarray) -> np.ndarray:
    """(P,) True where no saturated gyro row (:func:`saturated`; rows at ``t_g`` (G,) s, rates
    ``w`` (G,3) rad/s) lies within [``t_from``, ``t_to``] (P,) s."""
    sat = np.concatenate([[0], np.cumsum(saturated(w))])      # saturated rows before
    lo = np.searchsorted(t_g, t_from)
    hi = np.searchsorted(t_g, t_to, side="right")
    return sat[np.minimum(hi, len(t_g))] == sat[np.minimum(lo, len(t_g))]


def integrate_rates(t_g: np.ndarray, rates: np.ndarray) -> "Orientation":
    """Q (body → gyro-following frame, Q = I at the first row) on the gyro rows ``t_g`` (G,) s
    from the body rates ``rates`` (G,3) rad/s: Q_{i+1} = Q_i exp(ω̄_i Δt_i) with ω̄_i the
    average of rows i and i+1 (the trapezoidal rule on the rates)."""
    steps = 0.5 * (rates[1:] + rates[:-1]) * np.diff(t_g)[:, None]
    Q = cumulative_rotation(Rotation.from_rotvec(np.vstack([np.zeros(3), steps])))
    return Orientation(t_g, Q.as_quat(), steps)


class Orientation:
    """Q(t) from quaternions ``quat`` (G,4, scalar last) at the gyro rows ``t`` (G,) s and the
    rotation vectors ``steps`` (G−1,3) rad between them (Q_{i+1} = Q_i exp(steps_i)): at an
    instant inside row i's interval, Q_i exp(f·steps_i) — the slerp, without scipy's slow
    composition."""

    def __init__(self, t, quat, steps):
        self.t, self.quat, self.steps = t, quat, steps

    def at(self, t_query: np.ndarray) -> Rotation:

        i = np.clip(np.searchsorted(self.t, t_query) - 1, 0, len(self.t) - 2)
        f = np.clip((t_query - self.t[i]) / (self.t[i + 1] - self.t[i]), 0.0, 1.0)
        part = Rotation.from_rotvec(f[:, None] * self.steps[i]).as_quat()
        return Rotation.from_quat(qmul(self.quat[i], part))
