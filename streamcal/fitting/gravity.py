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
gravity-tied residual, the same with and without a registration effect; :func:`tilt_sigma`
estimates it from the recording (the motion and noise the accelerometer sees).

"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.integrate
import scipy.signal
from scipy.spatial.transform import Rotation

from ..errors import InsufficientDataError, MissingColumnsError
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
    with per-sample ``trust`` (A,) in (0, 1]; ``method`` says how it was made. ``tilt``
    (rad) and ``tilt_method``: its own error per horizontal axis (:func:`tilt_sigma`; NaN:
    not computed)."""

    t: np.ndarray
    down: np.ndarray
    trust: np.ndarray
    method: str
    tilt: float = float("nan")
    tilt_method: str = ""

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


def _specific_force(track) -> tuple[np.ndarray, np.ndarray]:
    """IMU instants ``t`` (A,) s, strictly increasing, and the specific force (A,3) in g (the
    median norm is 1 g, whatever the unit)."""
    rows = track.accel_rows
    t = np.asarray(track.t[rows], dtype=float)
    keep = np.r_[True, np.diff(t) > 0]
    f = np.asarray(track.accel, dtype=float)[keep]
    return t[keep], f / np.median(np.linalg.norm(f, axis=1))


#: Degrees of freedom the level of the vertical motion's spectrum is measured with: over a
#: band at least ``MIN_DOF / (2 × duration)`` wide (Hz), wider than the reference's own
#: low-pass on a short recording.
MIN_DOF = 60


def _filter_constants() -> tuple[float, float, float]:
    """``(∫|H|² du, ∫u²|H|² du, ∫|1 − H|²/u² du)`` over all u = f/fc for the zero-phase
    second-order Butterworth low-pass ``H(u) = 1 / (1 + u⁴)`` (sosfiltfilt squares the
    magnitude)."""
    def over_all_u(g):
        return 2.0 * scipy.integrate.quad(g, 0.0, np.inf)[0]

    return (over_all_u(lambda u: 1.0 / (1.0 + u ** 4) ** 2),
            over_all_u(lambda u: u ** 2 / (1.0 + u ** 4) ** 2),
            over_all_u(lambda u: u ** 6 / (1.0 + u ** 4) ** 2))


_PASS, _RATE, _STOP_OVER_F2 = _filter_constants()


def tilt_sigma(track) -> tuple[float, str]:
    """``(σ_tilt, how)``: the rms error (rad) of :func:`gravity_reference`'s down direction
    about one horizontal axis, estimated from the recording, and how, in words.

    Two parts, added in variance:

    - *Motion and noise passed by the low-pass.* The linear acceleration and the
      accelerometer noise that pass the reference's low-pass tilt it by their horizontal
      components over g. Their vertical component is measured at every frequency,
      ``‖f‖/g − 1`` (to first order). Assuming them isotropic (the same spectrum horizontally
      as vertically; white noise is) and their spectrum flat near the cut-off fc (true of noise
      and of motion correlated over less than 1/fc), the variance per horizontal component is
      ``var(LP_w(‖f‖/g − 1)) · fc / w``: the vertical one low-passed by the same filter at
      ``w = max(fc, MIN_DOF / (2 × duration))`` — a band wide enough to measure the spectrum's
      level with :data:`MIN_DOF` degrees of freedom — scaled to the reference's bandwidth.
      Without a gyro the filter is :data:`CUTOFF_ACCEL_HZ` and samples are weighted by the
      reference's trust.
    - *Drift of the gyro-following frame* (with a gyro). Gravity is constant in that frame only
      as far as the integrated gyro is right; the frame's drift φ (gyro gain, bias and noise
      errors, integrated) moves it, and the reference follows φ's slow part only. The
      reference's own estimate of gravity in that frame, LP(q f), tilts at the rate of φ's
      followed part plus that of the motion the low-pass passes; the motion's share is known
      from the first part (per horizontal component ``(2π fc)² ∫u²|H|²/∫|H|²`` times its
      variance, u = f/fc) and taken off. For a drift rate with a flat spectrum near fc (a
      random walk of angle) the part not followed has variance ``C · rate² / 2`` per
      horizontal component, rate² the mean squared tilt rate left, ``C = ∫ |1 − H|² / (2π f)²
      df / ∫ |H|² df`` for the filter H (= 1/(2π fc)², ≈ 10 s² at 0.05 Hz).

    What the gyro-following frame cannot see (a tilt of the accelerometer itself) is the
    misalignment the registration fit estimates, not noise.

    :func:`gravity_reference` gives the same figure as its ``tilt``, the gyro integrated once
    for both."""
    if not track.has("accel"):
        raise MissingColumnsError("the gravity reference needs accelerometer columns "
                                  "(ax, ay, az), which the track lacks")
    t, f = _specific_force(track)
    return _tilt(t, f, _followed(track, t, f)[1] if track.has("gyro") else None)


def _tilt(t: np.ndarray, f: np.ndarray, followed: np.ndarray | None) -> tuple[float, str]:
    """:func:`tilt_sigma` from the IMU instants ``t`` (A,) s, the specific force ``f`` (A,3)
    in g and, with a gyro, its low-passed image in the gyro-following frame ``followed``
    (A,3; None without a gyro)."""
    excess = np.linalg.norm(f, axis=1) - 1.0
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    gyro = followed is not None
    cutoff = CUTOFF_GYRO_HZ if gyro else CUTOFF_ACCEL_HZ
    band = max(cutoff, MIN_DOF / (2.0 * duration)) if duration > 0 else cutoff
    weight = np.ones_like(excess) if gyro else 1.0 / (1.0 + (excess / TRUST_G) ** 2)
    passed = _lowpass(excess, t, band)
    mean = np.sum(weight * passed) / np.sum(weight)
    motion = np.sum(weight * (passed - mean) ** 2) / np.sum(weight) * cutoff / band
    how = (f"vertical specific force, low-passed at {band:.3g} Hz and scaled to the "
           f"reference's {cutoff:g} Hz")
    drift = 0.0
    if gyro:
        along = followed / np.linalg.norm(followed, axis=1, keepdims=True)
        rate = np.gradient(followed, t, axis=0)
        tilt_rate = rate - np.sum(rate * along, axis=1, keepdims=True) * along
        moved_by_motion = 2.0 * motion * (2.0 * np.pi * cutoff) ** 2 * _RATE / _PASS
        left = max(float(np.mean(np.sum(tilt_rate ** 2, axis=1))) - moved_by_motion, 0.0)
        drift = _STOP_OVER_F2 / (4.0 * np.pi ** 2 * cutoff ** 2 * _PASS) * left / 2.0
        how += "; drift of the gyro-following frame from the rate its gravity estimate moves"
    return float(np.sqrt(motion + drift)), how


def _gyro_frame(track, t: np.ndarray, f: np.ndarray):
    """Rotations body → gyro-following frame at the IMU instants ``t`` (A,) s: the gyro
    integrated (bias from still samples, when there are enough); ``f`` (A,3) in g."""
    gr = track.gyro_rows
    w = np.stack([np.interp(t, track.t[gr], track.gyro[:, i]) for i in range(3)], axis=1)
    norm = np.linalg.norm(f, axis=1)
    still = (np.linalg.norm(w, axis=1) < STILL_RATE) & (np.abs(norm - 1) < 0.02)
    if still.sum() >= 100:
        w = w - np.median(w[still], axis=0)
    steps = np.vstack([np.zeros(3), 0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None]])
    return cumulative_rotation(Rotation.from_rotvec(steps))


def _followed(track, t: np.ndarray, f: np.ndarray):
    """(q, the specific force ``f`` (A,3) in the gyro-following frame, low-passed at
    :data:`CUTOFF_GYRO_HZ`); q: body → that frame at the IMU instants ``t``."""
    q = _gyro_frame(track, t, f)
    return q, _lowpass(q.apply(f), t, CUTOFF_GYRO_HZ)


def gravity_reference(track) -> GravityReference:
    """The down direction from ``track``'s accelerometer (and gyro when present), with its own
    error ``tilt`` (:func:`tilt_sigma`; NaN with fewer than two IMU samples)."""
    if not track.has("accel"):
        raise MissingColumnsError("the registration effects need accelerometer columns "
                                  "(ax, ay, az), which the track lacks")
    t, f = _specific_force(track)
    norm = np.linalg.norm(f, axis=1)
    trust = 1.0 / (1.0 + ((norm - 1.0) / TRUST_G) ** 2)
    followed = None
    if track.has("gyro"):
        q, followed = _followed(track, t, f)
        up = q.inv().apply(followed)
        trust = np.ones_like(trust)  # the filter has removed the linear acceleration
        method = "gyro-aided zero-phase low-pass"
    else:
        up = _lowpass(f, t, CUTOFF_ACCEL_HZ)
        method = "zero-phase low-pass"
    down = -up / np.linalg.norm(up, axis=1, keepdims=True)
    tilt, how = _tilt(t, f, followed) if len(t) >= 2 else (float("nan"), "")
    return GravityReference(t, down, trust, method, tilt, how)


def joined(pieces: Sequence[GravityReference]) -> GravityReference:
    """One reference from references of separate stretches of one recording, each built on its
    own contiguous rows (time order, not overlapping), so no filter runs across the gaps
    between them. Its ``tilt`` is not computed (NaN): the caller knows the stretches' error."""
    pieces = [p for p in pieces if len(p.t)]
    if not pieces:
        raise InsufficientDataError("no accelerometer samples to build the gravity reference")
    return GravityReference(np.concatenate([p.t for p in pieces]),
                            np.concatenate([p.down for p in pieces]),
                            np.concatenate([p.trust for p in pieces]),
                            pieces[0].method + ", per contiguous stretch read")
