"""The named core parameters of a calibration (K, b): ``K_xx, K_xy, K_xz, K_yy, K_yz, K_zz``
(the upper-triangular K) and ``b_x, b_y, b_z`` (sensor unit), as the held-parameter fit, the
gyro link and the reports name them one by one."""
from __future__ import annotations

from typing import Sequence

import numpy as np

#: (name, (row, col)) of the K entries and (name, axis) of the b entries, in report order.
K_PARAMS = (("K_xx", (0, 0)), ("K_xy", (0, 1)), ("K_xz", (0, 2)), ("K_yy", (1, 1)),
            ("K_yz", (1, 2)), ("K_zz", (2, 2)))
B_PARAMS = (("b_x", 0), ("b_y", 1), ("b_z", 2))
K_INDEX = dict(K_PARAMS)
B_INDEX = dict(B_PARAMS)


def entry(K, b, name: str) -> float:
    """The value of the named entry of ``K`` (3,3) or ``b`` (3,)."""
    return float(K[K_INDEX[name]] if name in K_INDEX else b[B_INDEX[name]])


def with_entries(K, b, names: Sequence[str], values) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``K``, ``b`` with the named entries set to ``values``."""
    K, b = np.array(K, float), np.array(b, float)
    for name, v in zip(names, values):
        if name in K_INDEX:
            K[K_INDEX[name]] = v
        else:
            b[B_INDEX[name]] = v
    return K, b


def shifted(K, b, names: Sequence[str], deltas) -> tuple[np.ndarray, np.ndarray]:
    """Copies of ``K``, ``b`` with ``deltas`` added to the named entries."""
    K, b = np.array(K, float), np.array(b, float)
    for name, v in zip(names, deltas):
        if name in K_INDEX:
            K[K_INDEX[name]] += v
        else:
            b[B_INDEX[name]] += v
    return K, b
