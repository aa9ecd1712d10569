"""The result of a gravity- or gyro-tied fit (:mod:`.registration`, :mod:`.gyro_lag`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RegistrationFit:
    """Everything a gravity-tied fit learnt: ``calibration`` plus per-sample ``residuals``
    (N,3) sensor unit, ``directions`` (N,3) magnetometer frame, ``inliers`` (N,), the global
    ``rotation`` (3,3, mag → accel), ``dip`` (rad), ``lag`` (s) and the number of global
    parameters ``n_params``; ``status``, ``iterations`` and ``message`` say how the
    solver ended."""

    calibration: object
    residuals: np.ndarray
    directions: np.ndarray
    inliers: np.ndarray
    rotation: np.ndarray
    dip: float
    lag: float
    n_params: int
    rms: float
    #: solver outcome (:data:`streamcal.fitting.damped_lm.STATUSES`), rounds used, in words
    status: str = "converged"
    iterations: int = 0
    message: str = ""
