"""SampleBlock: the one currency between sample sources and the streaming calibrator."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np


@dataclass(frozen=True, eq=False)
class SampleBlock:
    """A few consecutive samples, columnar.

    Attributes (n = number of instants, NaN where a sensor was not sampled at that instant):
        t: (n,) seconds, non-decreasing.
        mag: (n,3) magnetic field, µT, body (accelerometer) axes.
        accel: (n,3) specific force, m/s², body axes.
        gyro: (n,3) angular rate, rad/s, body axes.
        temp: (n,) die temperature, °C.
        aux: auxiliary channels {name: (n,)} (motor current, PWM duty…).
        source: where the samples came from (``"i2c:1:0x68"``, ``"serial:/dev/ttyACM0"``…).
    """

    t: np.ndarray
    mag: np.ndarray
    accel: np.ndarray | None = None
    gyro: np.ndarray | None = None
    temp: np.ndarray | None = None
    aux: Mapping[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    def __len__(self) -> int:
        return int(np.shape(self.t)[0])

    @property
    def mag_valid(self) -> np.ndarray:
        """(n,) bool: rows that carry a magnetometer sample."""
        return np.all(np.isfinite(self.mag), axis=1)
