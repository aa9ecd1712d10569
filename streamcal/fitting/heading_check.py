"""Does a refined calibration point the compass better or worse than the one it refines?

A calibration refined on a slice of the sphere (``streamcal fit FLIGHT --cal CAL``) is fitted to
the field's magnitude: the magnitude cannot see a small rotation of the field, so a refinement
that lowers the magnitude's rms may still turn the heading. Where the log has an attitude and a
place, the attitude reference (:mod:`.attitude_reference`) sees the direction: the heading
error of both calibrations against it, on the same samples (the reference fit's inliers).
"""
from __future__ import annotations

from ..calibration import Calibration
from .attitude_reference import attitude_reference

#: The refined calibration is called worse when its heading error rms exceeds the given one's
#: by more than this (degrees) and by more than :data:`WORSE_FRACTION` of it.
WORSE_DEG = 0.5
WORSE_FRACTION = 0.1


def worse_rule() -> str:
    """The rule of :func:`heading_check`'s ``worse``, in words."""
    return (f"worse when the refined calibration's heading error rms exceeds the given one's "
            f"by more than {WORSE_DEG:g}° and {100 * WORSE_FRACTION:g} %")


def heading_check(track, given: Calibration | None, refined: Calibration,
                  ref: dict | None = None) -> dict:
    """Heading error (degrees) of ``given`` and ``refined`` against the attitude reference of
    ``track`` (``ref``: :func:`streamcal.geomag.wmm_field` overriding the log's GPS place).

    Returns ``{"rms_before", "rms_after", "p95_before", "p95_after", "n", "worse", "rule"}``
    ("before" = ``given``, or the readings as logged when None), or ``{"reason": why not}``
    when the log has no attitude or no place."""
    out = attitude_reference(track, given, refined, ref=ref, detect=False)["attitude_reference"]
    heading = out.get("heading_error_deg")
    if not heading or heading.get("rms_after") is None:
        return {"reason": out.get("reason") or "no attitude reference"}
    before, after = heading["rms_before"], heading["rms_after"]
    worse = after > before + max(WORSE_DEG, WORSE_FRACTION * before)
    return {"rms_before": before, "rms_after": after, "p95_before": heading["p95_before"],
            "p95_after": heading["p95_after"], "n": out["n"], "worse": bool(worse),
            "rule": worse_rule()}
