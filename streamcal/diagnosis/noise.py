"""The noise floor, estimated from the data itself.

For white noise of standard deviation σ on an axis, the second difference
``m_{j+1} − 2 m_j + m_{j−1}`` has standard deviation σ√6, while a smooth motion contributes only
``B ω² Δt²`` (≈ 0.005 µT at 100 Hz and 1 rad/s). So per axis

    σ_i = rms(Δ²m_i within 4.5 robust σ of the median) / √6

(the MAD sets the window, so the odd jump or outlier does not count). When a gyro is present and the track has enough still
samples, only triplets where the sensor is still are used, which removes the motion part at low
sample rates. When readings are quantized (values on a grid of step LSB) and the noise is below
the LSB, the second differences are mostly zero; the quantization noise LSB²/12 is then the floor.

The floor reported is ``sqrt(mean_i σ_i²)``: the residual of the calibration (the distance of a
reading to the fitted ellipsoid, paper eq. 41) keeps one of the three noise components — the one
along the ellipsoid normal — whose variance, averaged over directions, is ``trace(Σ)/3``. So a
model that explains everything has ``rms ≈ noise_floor``: like is compared with like.

Whether the recording can measure it: white noise makes the second differences of consecutive
triplets correlated at lag 1 by exactly −2/3; motion between samples (a hand-turned sensor read
a few times a second) makes them smooth, with a lag-1 correlation near 0 or above. When the
mean correlation is above :data:`WHITE_D2_MAX` the second differences measure the motion, not
the noise: the floor is then not reliable (``floor`` NaN, ``measured`` keeps the number, and
``reason`` says why in words).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import MAD_TO_SIGMA, STILL_RATE
#: Fewest still triplets to prefer the still-only estimate.
MIN_STILL = 50
#: Lag-1 correlation of the second differences of white noise.
WHITE_D2_CORR = -2.0 / 3.0
#: Above this mean lag-1 correlation the second differences hold motion, not only noise.
WHITE_D2_MAX = -0.45


@dataclass(frozen=True)
class NoiseFloor:
    """Per-axis noise σ (3,) and the floor comparable with ``rms`` (sensor unit)."""

    sigma_axes: np.ndarray
    floor: float
    lsb: np.ndarray
    method: str
    n_used: int
    #: False when the recording cannot measure the floor (``floor`` is then NaN); ``reason``
    #: says why, ``measured`` is the (motion-contaminated) number the estimate gave.
    reliable: bool = True
    reason: str = ""
    measured: float = float("nan")
    d2_corr: float = float("nan")


def estimate_lsb(values: np.ndarray) -> float:
    """Grid step of ``values`` (N,) when they are quantized (also when printed with a few
    decimals, which blurs the grid slightly), else 0."""
    u = np.unique(values[np.isfinite(values)])
    if u.size < 2:
        return 0.0
    step = float(np.min(np.diff(u)))
    span = float(u[-1] - u[0])
    if step <= 0 or span / step > 1e6:
        return 0.0
    step = span / round(span / step)  # refined over the whole span
    ratio = (u - u[0]) / step
    on_grid = np.mean(np.abs(ratio - np.round(ratio)) < 0.05)
    return step if on_grid > 0.99 else 0.0


def noise_floor(m: np.ndarray, t: np.ndarray | None = None,
                gyro: np.ndarray | None = None) -> NoiseFloor:
    """Noise of readings ``m`` (N,3, sensor unit) at times ``t`` (N,) s; ``gyro`` (N,3) rad/s at
    the same instants, optional."""
    m = np.asarray(m, dtype=float)
    ok = np.ones(max(len(m) - 2, 0), bool)
    if t is not None and len(m) > 2:
        dt = np.diff(np.asarray(t, dtype=float))
        typical = np.median(dt)
        ok &= (dt[1:] < 3 * typical) & (dt[:-1] < 3 * typical)  # no gaps inside a triplet
    method = "second differences"
    if gyro is not None and len(m) > 2:
        still = np.linalg.norm(np.asarray(gyro, dtype=float), axis=1) < STILL_RATE
        triplet_still = still[2:] & still[1:-1] & still[:-2] & ok
        if triplet_still.sum() >= MIN_STILL:
            ok, method = triplet_still, "second differences over still samples"
    d2 = (m[2:] - 2 * m[1:-1] + m[:-2])[ok]
    if len(d2) < 3:
        nan = np.full(3, np.nan)
        return NoiseFloor(nan, float("nan"), np.zeros(3), "too few samples", len(d2),
                          reliable=False, reason=f"only {len(d2)} usable triplets of "
                          "consecutive samples: too few to measure the noise")
    lsb = np.array([estimate_lsb(m[:, i]) for i in range(3)])
    med = np.median(d2, axis=0)
    dev = np.abs(d2 - med)
    # The MAD rejects jumps but moves in LSB steps on quantized data; the rms of the deviations
    # inside a 4.5σ window keeps its robustness without that coarseness.
    window = np.maximum(4.5 * MAD_TO_SIGMA * np.median(dev, axis=0), 3 * lsb)
    inside = dev <= np.where(window > 0, window, np.inf)
    sigma = np.sqrt(np.sum(np.where(inside, dev, 0.0) ** 2, axis=0)
                    / np.maximum(inside.sum(axis=0), 1)) / np.sqrt(6.0)
    sigma = np.sqrt(np.maximum(sigma ** 2, lsb ** 2 / 12.0))
    floor = float(np.sqrt(np.mean(sigma ** 2)))
    corr = _lag1_corr(np.where(inside, d2 - med, 0.0), ok)
    if np.isfinite(corr) and corr > WHITE_D2_MAX:
        rate = 1.0 / float(np.median(np.diff(t))) if t is not None and len(t) > 1 else float("nan")
        hz = f" at {rate:.3g} Hz" if rate == rate else ""
        reason = (f"consecutive second differences of the readings{hz} correlate at {corr:.2f} "
                  f"where independent noise gives {WHITE_D2_CORR:.2f} (measurable only below "
                  f"{WHITE_D2_MAX:.2f}): {_why_not_white(m)}, so the {floor:.3g} they give is "
                  f"not the noise")
        return NoiseFloor(sigma, float("nan"), lsb, method, len(d2), reliable=False,
                          reason=reason, measured=floor, d2_corr=corr)
    return NoiseFloor(sigma, floor, lsb, method, len(d2), measured=floor, d2_corr=corr)


#: More repeated readings than this share means the log is faster than the sensor updates.
REPEAT_SHARE = 0.1


def _why_not_white(m: np.ndarray) -> str:
    """Why consecutive readings (N,3) are not independent noise, in words."""
    repeats = float(np.mean(np.all(m[1:] == m[:-1], axis=1))) if len(m) > 1 else 0.0
    if repeats > REPEAT_SHARE:
        return (f"{100 * repeats:.0f}% of the readings repeat the previous one exactly (logged "
                f"faster than the sensor updates)")
    return ("the sensor moves between samples and no still segment was found, or the readings "
            "are filtered or interpolated")


def _lag1_corr(d: np.ndarray, ok: np.ndarray) -> float:
    """Mean over the axes of the lag-1 correlation of the second differences ``d`` (n,3, the
    triplets kept by ``ok`` (n,)), over pairs of triplets that are neighbours in time."""
    pos = np.flatnonzero(ok)
    if len(pos) < 3:
        return float("nan")
    adjacent = np.diff(pos) == 1
    if adjacent.sum() < 2:
        return float("nan")
    a, b = d[:-1][adjacent], d[1:][adjacent]
    den = np.sqrt(np.sum(a * a, axis=0) * np.sum(b * b, axis=0))
    good = den > 0
    if not good.any():
        return float("nan")
    return float(np.mean(np.sum(a * b, axis=0)[good] / den[good]))
