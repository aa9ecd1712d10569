"""Which residual a calibration's rms is on, and its rms on the sensor residual.

``streamcal.fit`` returns, for a model with a registration effect (``time_lag``,
``mag_accel_misalignment``), the gravity- or gyro-tied fit: its ``rms`` is on that tied
residual (each direction tied to the accelerometer's gravity or carried by the gyro), which
includes the reference's own error and is not comparable with the sensor residual (eq. 41,
every direction free) of a plain fit. Every rms shown names its residual
(:data:`streamcal.diagnosis.diagnosis.RESIDUAL_LABELS`).
"""
from __future__ import annotations

import numpy as np

from ..calibration import rms_residual
from .residuals import rms, sensor_residual


def calibration_residual(cal) -> str:
    """``"sensor"``, ``"gravity_tied"`` or ``"gyro_tied"``: the residual ``cal.rms`` is on
    (:func:`streamcal.calibration.rms_residual`)."""
    return rms_residual(cal)


def sensor_rms(cal, track) -> float:
    """rms (sensor unit) of ``cal`` on the sensor residual (eq. 41) over its inliers (all
    samples when it has none per sample) of ``track``'s magnetometer readings."""
    m = np.asarray(track.mag, dtype=float)
    cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
    cov.setdefault("t", np.asarray(track.t_mag, dtype=float))
    r = sensor_residual(cal, m, cov)[0]
    inl = getattr(cal, "inliers", None)
    mask = np.asarray(inl, bool) if inl is not None and np.shape(inl) == (len(m),) else None
    return rms(r, mask)
