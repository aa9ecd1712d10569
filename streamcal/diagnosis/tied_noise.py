"""The noise floor of the gravity- and gyro-tied residuals, estimated from the recording.

A tied residual (:mod:`streamcal.diagnosis.candidates`) keeps more than the magnetometer's
noise even when the model is right: its reference — the accelerometer's gravity, or the
direction carried over by the gyro — has errors of its own. Its floor is what it would hold
with a perfect model, in the sensor unit, from two parts added in variance:

- *gravity-tied* (each direction on the cone at the dip angle around the gravity reference, one
  free heading): of the magnetometer's three noise components the free heading absorbs one,
  so ``2 σ²`` stays (σ the magnetometer floor of :mod:`streamcal.diagnosis.noise`, the rms of
  the per-axis noise); an error ε of the reference's down direction about the horizontal axis
  that turns the cone towards the field moves the direction by ε, so ``R² σ_tilt²`` adds, R the
  field radius (|det K|^⅓) and σ_tilt the reference's error per horizontal axis
  (:func:`streamcal.fitting.gravity.tilt_sigma`: the motion and noise the accelerometer sees
  that pass the reference's low-pass, and the drift of the gyro-following frame):

      floor² = 2 σ² + R² σ_tilt²

- *gyro-tied* (sample b predicted from sample a, H seconds earlier, by the integrated gyro):
  the direction noise of both samples (two components each, ``4 σ²``) and the gyro's white
  noise integrated over H (per axis σ_ω² H Δt, Δt the gyro's sample interval, on the two axes
  across the direction):

      floor² = 4 σ² + 2 R² σ_ω² H Δt

  with σ_ω the gyro's noise, measured as the magnetometer's is (second differences over still
  samples). The gyro's gains, frame and bias are fitted with the residual, so they add nothing.

The floor is measurable when the magnetometer floor is (the same reason otherwise).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calibration import field_radius
from ..errors import InsufficientDataError, StreamcalError
from .noise import noise_floor

#: Share of each noise component a tied residual keeps, in units of σ²: the gravity-tied one
#: two of three, the gyro-tied one two of three for each of its two samples.
MAG_SHARE = {"gravity_tied": 2.0, "gyro_tied": 4.0}


@dataclass(frozen=True)
class TiedFloor:
    """The floor of one tied ``residual`` (sensor unit; NaN when not ``reliable``, ``reason``
    then says why) and its two parts: ``magnetometer`` (the magnetometer noise it keeps) and
    ``reference`` (the reference's error), ``method`` how the reference part was measured."""

    residual: str
    floor: float
    magnetometer: float
    reference: float
    method: str
    reliable: bool = True
    reason: str = ""

    def to_dict(self) -> dict:
        def number(v):
            return float(v) if np.isfinite(v) else None

        return {"floor": number(self.floor) if self.reliable else None,
                "reliable": bool(self.reliable), "reason": self.reason,
                "magnetometer_part": number(self.magnetometer),
                "reference_part": number(self.reference), "method": self.method}


def tied_floor(residual: str, track, K: np.ndarray, mag_sigma: float, mag_reliable: bool,
               mag_reason: str = "", horizon_s: float | None = None,
               gravity=None) -> TiedFloor:
    """The floor of ``residual`` ("gravity_tied" or "gyro_tied") on ``track`` for a
    calibration with sensor matrix ``K`` (3,3): ``mag_sigma`` the magnetometer floor (sensor
    unit, the rms of the per-axis noise; ``mag_reliable``/``mag_reason`` whether it was
    measurable), ``horizon_s`` the gyro-tied pairs' horizon (s); ``gravity`` the
    :class:`~streamcal.fitting.gravity.GravityReference` used, whose own ``tilt`` is taken
    when it carries one (:func:`~streamcal.fitting.gravity.gravity_reference` measures it with
    the reference; a subsample's is measured on the contiguous stretches read)."""
    radius = field_radius(K)
    magnetometer = float(np.sqrt(MAG_SHARE[residual]) * mag_sigma)
    try:
        if residual == "gravity_tied":
            reference, method = _gravity_part(track, radius, gravity)
        else:
            reference, method = _gyro_part(track, radius, horizon_s)
    except StreamcalError as exc:
        return TiedFloor(residual, float("nan"), magnetometer, float("nan"), "", False,
                         f"the reference's error could not be estimated: {exc}")
    floor = float(np.hypot(magnetometer, reference))
    if not mag_reliable or not np.isfinite(floor):
        return TiedFloor(residual, float("nan"), magnetometer, reference, method, False,
                         mag_reason or "the magnetometer's noise floor could not be estimated")
    return TiedFloor(residual, floor, magnetometer, reference, method)


def _gravity_part(track, radius: float, gravity=None) -> tuple[float, str]:
    from ..fitting.gravity import tilt_sigma

    if gravity is not None and np.isfinite(gravity.tilt):
        sigma, how = gravity.tilt, gravity.tilt_method
    else:
        sigma, how = tilt_sigma(track)
    return radius * sigma, f"gravity reference: {how}"


def _gyro_part(track, radius: float, horizon_s: float | None) -> tuple[float, str]:
    from ..fitting.gyro_lag import HORIZON_S

    horizon = HORIZON_S if horizon_s is None else float(horizon_s)
    rows = np.asarray(track.gyro_rows, bool)
    t = np.asarray(track.t, float)[rows]
    w = np.asarray(track.gyro, float)
    nf = noise_floor(w, t, w)
    sigma = nf.floor if nf.reliable else nf.measured
    if not np.isfinite(sigma):
        raise InsufficientDataError(nf.reason or "the gyro's noise could not be measured")
    dt = float(np.median(np.diff(t)))
    part = radius * sigma * np.sqrt(2.0 * horizon * dt)
    return float(part), f"gyro noise {sigma:.3g} rad/s ({nf.method}) over {horizon:g} s"
