"""Do the compasses of one vehicle agree? Angles between their calibrated field vectors in time.

ArduPilot refuses to arm with "inconsistent compasses" when a compass used for yaw disagrees with
the primary by more than its limits (``Compass::consistent()`` in ``AP_Compass.cpp``, the limits
``AP_COMPASS_MAX_XYZ_ANG_DIFF``, ``AP_COMPASS_MAX_XY_ANG_DIFF`` and
``AP_COMPASS_MAX_XY_LENGTH_DIFF`` in ``AP_Compass.h``): the 3-D angle between the two corrected
field vectors over 90°, the angle between their body-frame X–Y components over 60°, or the length
of the difference of those X–Y components over 200 mG (20 µT). Those are the limits since
January 2017 (ArduPilot PR 5613, "relaxed compass consistency checks", first in Copter 3.5,
Plane 3.8 and Rover 3.2); before, ``consistent()`` applied 50°, 30° and 100 mG (10 µT).
:func:`limits_for` picks the limits of a log's firmware (:data:`OLD_LIMITS` for Copter < 3.5,
Plane < 3.8, Rover < 3.2; :data:`LIMITS` otherwise, and when the log names no ArduPilot version)
and says why.

For a pair of compasses ``a``, ``b`` of one log, each sample of ``a`` is paired with ``b``'s field
interpolated to its instant (``b`` sampled within :data:`MAX_GAP_S`), both corrected by a
calibration (the autopilot's in force, or streamcal's fit), and gives:

* ``angle_deg``: the 3-D angle between the two field vectors;
* ``xy_angle_deg``: the angle between their horizontal components, the plane perpendicular to
  gravity from the accelerometer at that instant (body X–Y when the log has no accelerometer;
  ``xy_plane`` says which);
* ``inconsistent``: over any of ArduPilot's limits, applied as the firmware applies them
  (3-D angle; body X–Y angle and X–Y length difference).

Fields are compared in the body frame: the autopilot's corrected field (the frame rotation a
calibration's canonical form carries in ``extra["frame_rotation_Q"]`` undone). streamcal's own
fit determines a compass's directions up to the rotation its upper-triangular ``K`` fixes, which
differs from the body frame by about the size of the off-diagonal soft iron (a few degrees).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: ArduPilot's consistency limits (AP_Compass.h) since January 2017: 3-D angle, body X–Y angle
#: (degrees), body X–Y length difference (µT; 200 mG).
LIMITS = {"angle_deg": 90.0, "xy_angle_deg": 60.0, "xy_length_uT": 20.0}
#: The limits before (AP_COMPASS_MAX_XYZ_ANG_DIFF 50°, AP_COMPASS_MAX_XY_ANG_DIFF 30°,
#: AP_COMPASS_MAX_XY_LENGTH_DIFF 100 mG = 10 µT), relaxed by ArduPilot PR 5613 (2017-01-26).
OLD_LIMITS = {"angle_deg": 50.0, "xy_angle_deg": 30.0, "xy_length_uT": 10.0}
#: The first release of each vehicle built with :data:`LIMITS`: Copter 3.5-rc1 (28 Jan 2017, its
#: release notes: "Relaxed compass calibration and compass consistency checks"); Plane 3.8 (its
#: betas from spring 2017; 3.7.1 was released in October 2016); Rover 3.2 (the first Rover
#: release from master after the change; 3.1.x came from a branch of 2016).
RELAXED_FROM = {"copter": (3, 5), "plane": (3, 8), "rover": (3, 2)}
#: Copter 3.3's pre-arm check calls ``Compass::consistent()``; what older releases compared is
#: not established here, so their :data:`OLD_LIMITS` are said to be an assumption.
CONSISTENT_KNOWN_FROM = {"copter": (3, 3)}
#: A sample of ``a`` is paired only when ``b`` has a sample within this time, s.
MAX_GAP_S = 0.25


def _limits_text(limits: dict) -> str:
    return (f"3-D angle {limits['angle_deg']:g} deg, body X-Y angle {limits['xy_angle_deg']:g} "
            f"deg, body X-Y length difference {10 * limits['xy_length_uT']:g} mG = "
            f"{limits['xy_length_uT']:g} uT")


LIMITS_TEXT = ("ArduPilot's consistency limits (AP_Compass.h, Compass::consistent): "
               + _limits_text(LIMITS))


@dataclass(frozen=True)
class ConsistencyLimits:
    """The limits a comparison applies: ``angle_deg``, ``xy_angle_deg`` (degrees),
    ``xy_length_uT`` (µT) and ``why`` (which firmware's limits, and why those)."""

    angle_deg: float
    xy_angle_deg: float
    xy_length_uT: float
    why: str

    def values(self) -> dict:
        """``{"angle_deg", "xy_angle_deg", "xy_length_uT"}``."""
        return {"angle_deg": self.angle_deg, "xy_angle_deg": self.xy_angle_deg,
                "xy_length_uT": self.xy_length_uT}

    def to_dict(self) -> dict:
        """The SPEC §6 ``consistency_limits`` object: the values and ``why``."""
        return {**self.values(), "why": self.why}

    @property
    def text(self) -> str:
        """One line: the limits and why."""
        return (f"ArduPilot's consistency limits (Compass::consistent): "
                f"{_limits_text(self.values())} ({self.why})")


CURRENT = ConsistencyLimits(**LIMITS, why="the current limits")


def limits_for(firmware: str | None, input_format: str | None = "ardupilot-dataflash"
               ) -> ConsistencyLimits:
    """The limits of the firmware named by ``firmware`` (its version text as logged, e.g.
    "APM:Copter V3.4.6"): :data:`OLD_LIMITS` before :data:`RELAXED_FROM`, else :data:`LIMITS`;
    :data:`LIMITS` too, said so, for a log of another autopilot or one naming no ArduPilot
    version."""
    from ..inputs.autopilot_cal import FIRMWARE_VERSION

    if input_format is not None and input_format != "ardupilot-dataflash":
        return ConsistencyLimits(**LIMITS, why="not an ArduPilot log: ArduPilot's current "
                                                "limits as a yardstick")
    match = FIRMWARE_VERSION.search(firmware or "")
    if not match:
        return ConsistencyLimits(**LIMITS, why="no ArduPilot version in the log: the current "
                                                "limits assumed")
    vehicle, version = match.group(1).lower(), (int(match.group(2)), int(match.group(3)))
    name = f"{vehicle.capitalize()} {version[0]}.{version[1]}"
    first = RELAXED_FROM.get(vehicle)
    if first is None:
        return ConsistencyLimits(**LIMITS, why=f"{name}: the current limits assumed")
    if version < first:
        known = CONSISTENT_KNOWN_FROM.get(vehicle)
        caveat = ("; the oldest limits known, assumed: this firmware's own check is not "
                  "established" if known and version < known else "")
        return ConsistencyLimits(**OLD_LIMITS, why=(
            f"{name}, before the limits were relaxed in {vehicle.capitalize()} "
            f"{first[0]}.{first[1]}{caveat}"))
    return ConsistencyLimits(**LIMITS, why=f"{name}: the limits since "
                                            f"{vehicle.capitalize()} {first[0]}.{first[1]}")


@dataclass
class CompassField:
    """One compass's calibrated field: ``t`` (N,) log time s, ``field_uT`` (N,3) body frame,
    ``gravity`` (N,3) accelerometer at those instants or None, ``instance``."""

    instance: int
    t: np.ndarray
    field_uT: np.ndarray
    gravity: np.ndarray | None = None


@dataclass
class PairConsistency:
    """The comparison of compasses ``a`` and ``b`` under one ``calibration`` label: per paired
    sample ``t`` (s), ``angle_deg``, ``xy_angle_deg``, ``inconsistent`` (bool)."""

    a: int
    b: int
    calibration: str
    xy_plane: str
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    angle_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    xy_angle_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    inconsistent: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    #: whether ArduPilot's own test compares this pair (one of them the primary, both used for
    #: yaw); None for a log of another autopilot
    ardupilot_checks: bool | None = None
    #: the limits ``inconsistent`` applies
    limits: ConsistencyLimits = CURRENT

    def to_dict(self) -> dict:
        """The SPEC §6 ``consistency`` entry (None for the statistics of an empty pairing)."""
        n = len(self.t)

        def stat(values, q):
            return float(np.percentile(values, q)) if n else None

        return {"a": self.a, "b": self.b, "calibration": self.calibration, "n": n,
                "angle_deg_median": stat(self.angle_deg, 50),
                "angle_deg_p95": stat(self.angle_deg, 95),
                "xy_angle_deg_median": stat(self.xy_angle_deg, 50),
                "xy_angle_deg_p95": stat(self.xy_angle_deg, 95),
                "fraction_inconsistent": float(np.mean(self.inconsistent)) if n else None,
                "xy_plane": self.xy_plane, "ardupilot_checks": self.ardupilot_checks}


def calibrated_field(track, cal) -> tuple[np.ndarray, np.ndarray]:
    """``(t_mag (N,) s, field (N,3) µT)``: ``cal`` applied to the track's magnetometer samples,
    rotated back to the frame of the readings when ``cal`` carries ``frame_rotation_Q``."""
    cov = track.covariates_at_mag()
    f = cal.apply_field(np.asarray(track.mag, float), cov)
    Q = (cal.extra or {}).get("frame_rotation_Q")
    if Q is not None:
        f = f @ np.asarray(Q, float)      # x_K = Q x_body  →  x_body = Qᵀ x_K (row vectors)
    return np.asarray(track.t_mag, float), f


def compass_field(track, cal, instance: int, t_offset: float = 0.0) -> CompassField:
    """A :class:`CompassField` of ``track`` under ``cal``; ``t_offset`` s is added to the
    track's times (its log time origin) so that compasses of one log share a clock."""
    t, f = calibrated_field(track, cal)
    gravity = None
    if track.has("accel"):
        cov = track.covariates_at_mag()
        if all(k in cov for k in ("ax", "ay", "az")):
            gravity = np.column_stack([cov["ax"], cov["ay"], cov["az"]])
    return CompassField(instance, t + t_offset, f, gravity)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angles (N,) in degrees between rows of ``u`` and ``v`` (2-D or 3-D), atan2-based."""
    if u.shape[1] == 2:
        cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
        return np.degrees(np.abs(np.arctan2(cross, np.sum(u * v, axis=1))))
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.sum(u * v, axis=1)))


def _paired(a: CompassField, b: CompassField) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``a`` that have a ``b`` sample within :data:`MAX_GAP_S`, and ``b``'s field
    linearly interpolated to those instants (M,3)."""
    order = np.argsort(b.t, kind="stable")
    tb, fb = b.t[order], b.field_uT[order]
    if len(tb) == 0:
        return np.zeros(0, int), np.zeros((0, 3))
    j = np.clip(np.searchsorted(tb, a.t), 1, max(len(tb) - 1, 1))
    gap = np.minimum(np.abs(a.t - tb[j - 1]), np.abs(tb[np.minimum(j, len(tb) - 1)] - a.t))
    keep = np.flatnonzero((gap <= MAX_GAP_S) & (a.t >= tb[0] - MAX_GAP_S)
                          & (a.t <= tb[-1] + MAX_GAP_S))
    fb_at = np.column_stack([np.interp(a.t[keep], tb, fb[:, k]) for k in range(3)])
    return keep, fb_at


def compare(a: CompassField, b: CompassField, calibration: str,
            limits: ConsistencyLimits = CURRENT) -> PairConsistency:
    """The consistency of ``a`` and ``b`` under ``limits`` (see the module docstring)."""
    keep, fb = _paired(a, b)
    fa = a.field_uT[keep]
    angle = _angle_deg(fa, fb)
    body_xy_angle = _angle_deg(fa[:, :2], fb[:, :2])
    xy_length = np.linalg.norm(fa[:, :2] - fb[:, :2], axis=1)
    zero_xy = (np.linalg.norm(fa[:, :2], axis=1) == 0) | (np.linalg.norm(fb[:, :2], axis=1) == 0)
    inconsistent = ((angle > limits.angle_deg) | (body_xy_angle > limits.xy_angle_deg)
                    | (xy_length > limits.xy_length_uT) | zero_xy)
    if a.gravity is not None:
        g = a.gravity[keep]
        g = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
        ha = fa - np.sum(fa * g, axis=1, keepdims=True) * g
        hb = fb - np.sum(fb * g, axis=1, keepdims=True) * g
        xy_angle, plane = _angle_deg(ha, hb), "horizontal (perpendicular to the accelerometer)"
    else:
        xy_angle, plane = body_xy_angle, "body X-Y (no accelerometer in the log)"
    return PairConsistency(a.instance, b.instance, calibration, plane, a.t[keep], angle,
                           xy_angle, inconsistent, limits=limits)


def compare_all(fields: list[CompassField], calibration: str,
                limits: ConsistencyLimits = CURRENT) -> list[PairConsistency]:
    """Every pair ``a < b`` of ``fields`` (in their order) under one calibration label."""
    return [compare(fields[i], fields[j], calibration, limits)
            for i in range(len(fields)) for j in range(i + 1, len(fields))]
