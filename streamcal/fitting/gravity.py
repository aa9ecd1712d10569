"""The gravity ("down") direction in the accelerometer frame for the gravity-tied fit
(:mod:`streamcal.fitting.registration`).

The accelerometer measures specific force: gravity plus the hand's linear acceleration
(≈ 0.4 m/s², 2–3° of tilt error, several times the magnetometer noise). With a gyro, the readings
are rotated into a frame that follows the integrated gyro (bias taken from still samples),
low-passed there by a zero-phase filter (:data:`CUTOFF_GYRO_HZ`: gravity is constant in that
frame, the linear acceleration and — as the body turns — the accelerometer's own offset average
out) and rotated back: ≈ 1.3° rms on the simulated hand motion against 3.4° for the raw
direction. Without a gyro, a zero-phase low-pass of the readings and trust_j = 1 / (1 + (|‖a_j‖
− g| / 0.05 g)²) down-weight samples under strong acceleration. Zero-phase filters add no delay,
so τ is not biased. (An accelerometer ellipsoid fit first was tried and dropped: on hand-motion
data its linear acceleration tilts K by degrees.) The remaining error of ĝ is a floor of the
gravity-tied residual, the same with and without a registration effect.

"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal
from scipy.spatial.transform import Rotation

from ..errors import MissingColumnsError
from ..quaternion import cumulative_rotation

#: Low-pass cut-off (Hz) of the gravity estimate: in the gyro-following frame / raw readings.
CUTOFF_GYRO_HZ = 0.05
CUTOFF_ACCEL_HZ = 3.0
#: ‖a‖ deviation from 1 g (in g) at which a sample's trust halves.
TRUST_G = 0.05
#: ‖ω‖ (rad/s) below which a sample counts as still for the gyro bias.
STILL_RATE = 0.05


@dataclass(frozen=True)
class GravityReference:
    """Unit down direction ĝ (A,3) in the accelerometer frame at the IMU instants ``t`` (A,) s,
    with per-sample ``trust`` (A,) in (0, 1]; ``method`` says how it was made."""

    t: np.ndarray
    down: np.ndarray
    trust: np.ndarray
    method: str

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ĝ (M,3) unit, trust (M,)) at the instants ``t`` (M,) s, linear interpolation."""
        g = np.stack([np.interp(t, self.t, self.down[:, i]) for i in range(3)], axis=1)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        return g, np.interp(t, self.t, self.trust)


def _lowpass(values: np.ndarray, t: np.ndarray, cutoff_hz: float) -> np.ndarray:
    fs = 1.0 / float(np.median(np.diff(t)))
    if len(t) < 30 or cutoff_hz >= 0.45 * fs:
        return values
    sos = scipy.signal.butter(2, cutoff_hz, fs=fs, output="sos")
    return scipy.signal.sosfiltfilt(sos, values, axis=0)


def gravity_reference(track) -> GravityReference:
    """The down direction from ``track``'s accelerometer (and gyro when present)."""
    if not track.has("accel"):
        raise MissingColumnsError("the registration effects need accelerometer columns "
                                  "(ax, ay, az), which the track lacks")
    rows = track.accel_rows
    t = np.asarray(track.t[rows], dtype=float)
    keep = np.r_[True, np.diff(t) > 0]
    t = t[keep]
    f = np.asarray(track.accel, dtype=float)[keep]
    f = f / np.median(np.linalg.norm(f, axis=1))               # in g, whatever the unit
    norm = np.linalg.norm(f, axis=1)
    trust = 1.0 / (1.0 + ((norm - 1.0) / TRUST_G) ** 2)
    if track.has("gyro"):

        gr = track.gyro_rows
        w = np.stack([np.interp(t, track.t[gr], track.gyro[:, i]) for i in range(3)], axis=1)
        still = (np.linalg.norm(w, axis=1) < STILL_RATE) & (np.abs(norm - 1) < 0.02)
        if still.sum() >= 100:
            w = w - np.median(w[still], axis=0)
        steps = np.vstack([np.zeros(3), 0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None]])
        q = cumulative_rotation(Rotation.from_rotvec(steps))   # body → gyro-following frame
        up = q.inv().apply(_lowpass(q.apply(f), t, CUTOFF_GYRO_HZ))
        trust = np.ones_like(trust)  # the filter has removed the linear acceleration
        method = "gyro-aided zero-phase low-pass"
    else:
        up = _lowpass(f, t, CUTOFF_ACCEL_HZ)
        method = "zero-phase low-pass"
    down = -up / np.linalg.norm(up, axis=1, keepdims=True)
    return GravityReference(t, down, trust, method)
