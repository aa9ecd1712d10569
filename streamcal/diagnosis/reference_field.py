"""A diagnosis's fitted field set beside the local geomagnetic field (``--lat/--lon``).

The fitted strength is the calibration's ``field`` (else its radius, sensor unit); the fitted
dip is the median angle of the calibrated field below the plane normal to gravity, gravity from
the accelerometer (:func:`streamcal.fitting.gravity.gravity_reference`), over the calibration's
inliers. Words and JSON keys: :func:`streamcal.geomag.compare`.
"""
from __future__ import annotations

import numpy as np

from ..geomag import NO_LOCATION, compare


def fitted_dip(track, calibration, gravity=None) -> tuple[float | None, float | None]:
    """(median, robust spread) of the calibrated field's dip over the inliers, degrees; (None,
    None) without accelerometer columns. ``gravity``: the track's gravity reference when it
    cannot be built from its rows as one stretch (a subsample's); None builds it."""
    from ..fitting.gravity import gravity_reference
    from ..geomag import dip_deg

    if not track.has("accel") or not len(track.t_mag):
        return None, None
    gravity = gravity_reference(track) if gravity is None else gravity
    down, _ = gravity.at(np.asarray(track.t_mag, dtype=float))
    field = calibration.apply_field(track.mag, track.covariates_at_mag())
    inl = calibration.inliers
    if inl is not None and len(inl) == len(field):
        field, down = field[inl], down[inl]
    return dip_deg(field, down)


def reference_field(track, calibration, ref: dict | None, reason: str = NO_LOCATION,
                    gravity=None) -> dict:
    """The ``"reference_field"`` object of ``diagnose --json`` for ``calibration`` fitted to
    ``track`` against ``ref`` (:func:`streamcal.geomag.wmm_field`, or None: ``reason`` says
    why); ``gravity`` as for :func:`fitted_dip`."""
    if ref is None or calibration is None:
        return compare(None, None, "", reason=reason if ref is None
                       else "no calibration to compare")
    dip, spread = fitted_dip(track, calibration, gravity)
    return compare(ref, calibration.field or calibration.radius,
                   calibration.unit or track.mag_unit, dip, spread)
