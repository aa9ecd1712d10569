"""The named core parameters of a calibration (K, b): ``K_xx, K_xy, K_xz, K_yy, K_yz, K_zz``
(the upper-triangular K), ``b_x, b_y, b_z`` (sensor unit), as the held-parameter fit, the
gyro link and the reports name them one by one, and ``radius``: the field radius r of K (the
geometric mean of |diag K|, sensor unit), whose change scales the whole of K — the field
strength a calibration's shape is held at."""
from __future__ import annotations

from typing import Sequence

import numpy as np

#: (name, (row, col)) of the K entries and (name, axis) of the b entries, in report order.
K_PARAMS = (("K_xx", (0, 0)), ("K_xy", (0, 1)), ("K_xz", (0, 2)), ("K_yy", (1, 1)),
            ("K_yz", (1, 2)), ("K_zz", (2, 2)))
B_PARAMS = (("b_x", 0), ("b_y", 1), ("b_z", 2))
K_INDEX = dict(K_PARAMS)
B_INDEX = dict(B_PARAMS)
RADIUS = "radius"


def field_radius(K) -> float:
    """Geometric mean of |diag K| (sensor unit)."""
    return float(np.prod(np.abs(np.diag(K))) ** (1 / 3))


def entry(K, b, name: str) -> float:
    """The value of the named entry of ``K`` (3,3) or ``b`` (3,), or K's field radius."""
    if name == RADIUS:
        return field_radius(K)
    return float(K[K_INDEX[name]] if name in K_INDEX else b[B_INDEX[name]])


def with_entries(K, b, names: Sequence[str], values) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``K``, ``b`` with the named entries set to ``values`` (``radius``: K scaled to
    it, before the entries are set)."""
    K, b = np.array(K, float), np.array(b, float)
    pairs = sorted(zip(names, values), key=lambda nv: nv[0] != RADIUS)
    for name, v in pairs:
        if name == RADIUS:
            K *= v / field_radius(K)
        elif name in K_INDEX:
            K[K_INDEX[name]] = v
        else:
            b[B_INDEX[name]] = v
    return K, b


def shifted(K, b, names: Sequence[str], deltas) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``K``, ``b`` with ``deltas`` added to the named entries (``radius``: ``K`` given
    scaled by (r + δ)/r, r its field radius, before the entries are shifted)."""
    K, b = np.array(K, float), np.array(b, float)
    pairs = sorted(zip(names, deltas), key=lambda nv: nv[0] != RADIUS)
    for name, v in pairs:
        if name == RADIUS:
            K *= 1.0 + v / field_radius(K)
        elif name in K_INDEX:
            K[K_INDEX[name]] += v
        else:
            b[B_INDEX[name]] += v
    return K, b
