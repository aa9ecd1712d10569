"""Quaternion helpers shared by the simulator and the gyro-tied solvers (scalar-last, as scipy)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of scalar-last quaternions (..., 4). Written out because scipy's
    ``Rotation.__mul__`` costs ~0.2 s per 10⁵ compositions here, 30× this."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def cumulative_rotation(steps: Rotation) -> Rotation:
    """Prefix products ``P_k = steps[0] * steps[1] * … * steps[k]`` (Hillis–Steele scan:
    ⌈log₂ n⌉ vectorized compositions instead of a per-sample loop)."""
    acc = steps.as_quat()
    offset = 1
    while offset < len(acc):
        acc = np.concatenate([acc[:offset], qmul(acc[:-offset], acc[offset:])])
        offset *= 2
    return Rotation.from_quat(acc)  # normalizes the rounding drift
