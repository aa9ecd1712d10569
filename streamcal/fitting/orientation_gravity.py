"""A compass mounted rotated, seen from gravity alone (no attitude in the log): the angle of the
calibrated field below the plane normal to gravity (the dip) must be the World Magnetic Model's
inclination at every sample. Each mounting rotation of
:mod:`streamcal.inputs.mount_rotations` turns the field before the dip is taken; a wrong one
leaves a dip that is off and that changes with the vehicle's attitude.

Rotations that keep the axes gravity moves along give the same dips: a vehicle that stays level
cannot tell a yaw mounting (YAW_90…) from none. Those ties are reported (``ambiguous_with``),
and NONE wins a tie.
"""
from __future__ import annotations

import numpy as np

from ..inputs.mount_rotations import as_dict, mount_rotations

#: Candidates whose dip misfit is within this factor of the best one's (plus
#: :data:`TIE_FLOOR_DEG`) are ties.
TIE_FACTOR = 1.5
TIE_FLOOR_DEG = 0.5


def dip_misfit_deg(field: np.ndarray, down: np.ndarray, inclination_deg: float,
                   matrix: np.ndarray) -> float:
    """Robust rms (degrees) of ``dip − inclination`` over the samples with the field turned by
    ``matrix`` (sensor → body): ``field`` (N,3) calibrated, ``down`` (N,3) unit gravity."""
    f = np.asarray(field, float) @ np.asarray(matrix).T
    s = np.einsum("ij,ij->i", f, down) / np.linalg.norm(f, axis=1)
    d = np.degrees(np.arcsin(np.clip(s, -1.0, 1.0))) - inclination_deg
    return float(np.sqrt(np.median(d ** 2) / 0.4549))   # median of χ²₁ = 0.4549


def orientation_from_gravity(field, down, inclination_deg: float) -> dict:
    """The ``orientation`` object (docs/flight_logs.md) with ``"method": "gravity"``,
    ``angle_error_deg`` the best candidate's dip misfit and ``ambiguous_with`` the names of
    the candidates gravity cannot tell from it."""
    ok = np.all(np.isfinite(field), axis=1) & np.all(np.isfinite(down), axis=1)
    field, down = np.asarray(field)[ok], np.asarray(down)[ok]
    scores = [(dip_misfit_deg(field, down, inclination_deg, r.matrix), k, r)
              for k, r in enumerate(mount_rotations())]
    scores.sort(key=lambda s: (s[0], s[1]))
    limit = TIE_FACTOR * scores[0][0] + TIE_FLOOR_DEG
    ties = [s for s in scores if s[0] <= limit]
    best = next((s for s in ties if s[2].name == "NONE"), ties[0])
    out = as_dict(best[2], best[0])
    out["method"] = "gravity"
    out["ambiguous_with"] = [s[2].name for s in ties if s[2] is not best[2]]
    return out
