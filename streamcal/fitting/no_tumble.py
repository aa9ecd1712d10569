"""Calibration of a vehicle that cannot be tumbled, against the World Magnetic Model.

* **Known heading** (:func:`fit_heading`): a few still seconds at a known true heading (with a
  gyro, only the samples turning slower than ``STILL_RATE`` count). The
  accelerometer gives roll and pitch (gravity), the heading gives yaw, the model the field:
  the expected body-frame field ``e`` is known, and one attitude gives three equations —
  the offset ``b = median(m) − A e`` with the iron ``A`` held (a given calibration's, else the
  identity at the model's field strength).
* **Planar** (:func:`fit_planar`): a rover or boat turning in the plane. Roll and pitch come
  from the accelerometer; the calibrated field, levelled with them, must have the model's
  horizontal strength H and vertical component Z at every sample — an ellipse of known radius,
  fitted robustly. The turns (at least half a circle) give the horizontal offsets and iron,
  Z (total field and inclination) the vertical offset. Headings come from the compass itself,
  so a rotation about the vertical is not seen; the vertical scale and its cross terms are
  held at the identity because turning in the plane does not change the vertical field.

Each result lists what it could not determine in ``extra["undetermined"]``
(``{"PARAM": "the value assumed and why"}``).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..calibration import Calibration
from ..constants import CAUCHY_C, STILL_RATE
from ..errors import InsufficientDataError
from ..geomag import ned_field
from .attitude_reference import calibration_from_fit
from .reference_fit import ReferenceFit
from ..inputs.mount_rotations import mount_rotations

#: The planar fit refuses when a horizontal offset is less certain than this (µT, 1 σ), or
#: when the headings cover less than MIN_ARC_DEG of the circle (on simulated rovers an arc of
#: 150–175° left the offsets 0.8–1.3 µT off with σ ≈ 0.2 µT: the iron trades with them).
PLANAR_MAX_SIGMA_UT = 1.0
MIN_ARC_DEG = 180.0
#: Entries of the iron a vehicle turning in the plane cannot see (held at the identity).
VERTICAL_IRON = ("A33", "A13", "A23")
#: Median and 99.9 % point of a χ² with 2 degrees of freedom.
CHI2_2_MEDIAN, CHI2_2_INLIER = 1.3863, 13.816
#: Fewest magnetometer samples with an accelerometer sample for either fit.
MIN_SAMPLES = 10
#: ``--heading`` refuses still samples whose calibrated field points over more than this many
#: degrees of heading (5th to 95th percentile): they were not taken at one heading (noise
#: 0.4 µT on a 20 µT horizontal field spreads them by about 4°).
MAX_HEADING_SPREAD_DEG = 30.0


def _mag_and_down(track, still: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(m (M,3), down (M,3) unit gravity direction in the body frame) at the mag samples;
    with ``still`` and a gyro, only the samples turning slower than ``STILL_RATE``."""
    if not track.has("accel"):
        raise InsufficientDataError("the vertical comes from the accelerometer, and the track "
                                    "has none (ax, ay, az)")
    cov = track.covariates_at_mag()
    a = np.column_stack([cov[c] for c in ("ax", "ay", "az")])
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    ok = np.all(np.isfinite(a), axis=1) & (norm[:, 0] > 0)
    what = "magnetometer samples with gravity"
    if still and track.has("gyro"):
        w = np.linalg.norm(np.column_stack([cov[c] for c in ("gx", "gy", "gz")]), axis=1)
        ok &= w < STILL_RATE
        what = f"still magnetometer samples (gyro under {STILL_RATE:g} rad/s) with gravity"
    if ok.sum() < MIN_SAMPLES:
        raise InsufficientDataError(f"only {int(ok.sum())} {what} (need {MIN_SAMPLES})")
    return track.mag[ok], -a[ok] / norm[ok]        # at rest the accelerometer reads −g


def tilt_rotation(down: np.ndarray, yaw_deg) -> Rotation:
    """Attitudes (body → NED) with roll and pitch from ``down`` (M,3) and yaw ``yaw_deg``."""
    roll = np.degrees(np.arctan2(down[:, 1], down[:, 2]))
    pitch = np.degrees(np.arctan2(-down[:, 0], np.hypot(down[:, 1], down[:, 2])))
    yaw = np.broadcast_to(np.asarray(yaw_deg, float), roll.shape)
    return Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)


def _held_iron(initial: Calibration | None, field_uT: float) -> tuple[np.ndarray, str]:
    """Body-frame A (3,3) with ``m = A e + b``, and the words saying where it comes from."""
    if initial is None:
        return np.eye(3), ("held at the identity (no soft iron, unit gain at the model's "
                           f"{field_uT:.4g} µT): one attitude gives three equations, only "
                           "the offsets are solved; give --initial CAL to hold a known iron")
    Q = np.asarray((initial.extra or {}).get("frame_rotation_Q", np.eye(3)), float)
    return initial.K @ Q / field_uT, ("held at --initial's K (one attitude gives three "
                                      "equations, only the offsets are solved)")


def fit_heading(track, heading_deg: float, ref: dict, initial: Calibration | None = None) -> Calibration:
    """Offsets from a still vehicle at true heading ``heading_deg`` (degrees clockwise from
    true north) with the model field ``ref`` (:func:`streamcal.geomag.wmm_field`)."""
    m, down = _mag_and_down(track, still=True)
    b_ned = ned_field(ref)
    F = ref["intensity_uT"]
    e = tilt_rotation(down, heading_deg).inv().apply(b_ned)
    A, iron_why = _held_iron(initial, F)
    r = m - e @ A.T
    b = np.median(r, axis=0)
    resid = np.linalg.norm(r - b, axis=1)
    _one_heading(m, b, A, down)
    spread = float(np.degrees(np.ptp(np.arctan2(down[:, 1], down[:, 2]))))
    fit = ReferenceFit(rotation=mount_rotations()[0], A=A, b=b, weights=np.ones(len(m)),
                       rms=float(np.sqrt(np.mean(resid ** 2))), inliers=np.ones(len(m), bool))
    undetermined = {
        "K": iron_why,
        "orientation": "assumed NONE (the compass axes are the vehicle's): a single attitude "
                       "cannot tell a mounting rotation from an offset",
        "heading": f"taken as {heading_deg:g}° true as given; the offsets are only as good as "
                   "it (1° of heading moves them by about 1.7 % of the horizontal field)",
    }
    cal = calibration_from_fit(fit, F, f"still at a known heading of {heading_deg:g}° true "
                                       f"({len(m)} samples)", undetermined)
    extra = dict(cal.extra)
    extra["known_heading"] = {"heading_deg": heading_deg, "declination_deg": ref["declination_deg"],
                              "roll_span_deg": round(spread, 3), "reference": ref["source"]}
    return cal.replace(method="known_heading", kernel=None, extra=extra)


def _one_heading(m: np.ndarray, b: np.ndarray, A: np.ndarray, down: np.ndarray) -> None:
    """Refuse (InsufficientDataError) when the still samples ``m`` (M,3), corrected with ``b``
    and ``A`` and levelled with ``down`` (M,3), point over more than
    :data:`MAX_HEADING_SPREAD_DEG` of heading: a vehicle that turned between its still moments
    (a flight, a drive) gives offsets that fit no heading."""
    level = tilt_rotation(down, 0.0).apply(np.linalg.solve(A, (m - b).T).T)
    angle = np.arctan2(level[:, 1], level[:, 0])
    centre = np.angle(np.mean(np.exp(1j * angle)))
    turn = np.degrees(np.angle(np.exp(1j * (angle - centre))))
    spread = float(np.percentile(turn, 95) - np.percentile(turn, 5))
    if spread > MAX_HEADING_SPREAD_DEG:
        raise InsufficientDataError(
            f"--heading: the {len(m)} still samples point over {spread:.0f}° of heading (5th to "
            f"95th percentile; at most {MAX_HEADING_SPREAD_DEG:g}°), not at one heading: record "
            "a few still seconds at the known heading, or use --planar (a vehicle turning in "
            "the plane) or --attitude (a log with attitude and GPS)")


def heading_arc_deg(yaw_deg) -> float:
    """Degrees of the circle the headings cover: 360 minus the largest gap between them."""
    h = np.sort(np.mod(np.asarray(yaw_deg, float), 360.0))
    if len(h) < 2:
        return 0.0
    gaps = np.diff(np.r_[h, h[0] + 360.0])
    return float(360.0 - gaps.max())


def _planar_parts(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A (3,3), b (3,)) of the planar parameters (A11, A22, A12, bx, by, bz); the vertical
    row and column of A held at the identity's."""
    a11, a22, a12, bx, by, bz = theta
    return np.array([[a11, a12, 0.0], [a12, a22, 0.0], [0.0, 0.0, 1.0]]), np.array([bx, by, bz])


def _level_field(theta, m, tilt: Rotation) -> np.ndarray:
    """The calibrated field ``A⁻¹ (m − b)`` turned into a level frame (yaw unknown), (N,3)."""
    A, b = _planar_parts(theta)
    return tilt.apply(np.linalg.solve(A, (m - b).T).T)


def fit_planar(track, ref: dict) -> Calibration:
    """Offsets and horizontal iron of a vehicle turning in the plane (module docstring).

    A robust (Cauchy) least squares over (A11, A22, A12, bx, by, bz): the calibrated field,
    levelled with the accelerometer's roll and pitch, must have the model's horizontal
    strength H and vertical component Z at every sample — an ellipse of known radius, which
    locates the centre also from part of a circle. Raises InsufficientDataError when the
    horizontal offsets come out less certain than :data:`PLANAR_MAX_SIGMA_UT` (too short an
    arc of headings)."""
    from scipy.optimize import least_squares

    m, down = _mag_and_down(track)
    b_ned = ned_field(ref)
    F, H, Z = ref["intensity_uT"], float(np.hypot(b_ned[0], b_ned[1])), float(b_ned[2])
    tilt = tilt_rotation(down, 0.0)

    def residual(theta):
        g = _level_field(theta, m, tilt)
        return np.concatenate([np.hypot(g[:, 0], g[:, 1]) - H, g[:, 2] - Z])

    centre = (np.percentile(m, 97.5, axis=0) + np.percentile(m, 2.5, axis=0)) / 2
    theta = np.array([1.0, 1.0, 0.0, centre[0], centre[1], np.median(m[:, 2]) - Z])
    scale = 5.0
    for _ in range(3):      # the Cauchy width follows the robust scale of the residual
        sol = least_squares(residual, theta, loss="cauchy", f_scale=CAUCHY_C * scale,
                            x_scale=[0.1, 0.1, 0.1, 10.0, 10.0, 10.0])
        theta = sol.x
        r = sol.fun.reshape(2, -1).T
        r2 = np.sum(r * r, axis=1)
        scale = max(float(np.sqrt(np.median(r2) / CHI2_2_MEDIAN)), 1e-3)
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J) * scale ** 2
    sigma = np.sqrt(np.diag(cov))
    g = _level_field(theta, m, tilt)
    arc = heading_arc_deg(np.degrees(np.arctan2(b_ned[1], b_ned[0]) - np.arctan2(g[:, 1], g[:, 0])))
    if arc < MIN_ARC_DEG or max(sigma[3], sigma[4]) > PLANAR_MAX_SIGMA_UT:
        raise InsufficientDataError(
            f"--planar: {arc:.0f}° of heading (need {MIN_ARC_DEG:g}°) give the horizontal "
            f"offsets to ±{max(sigma[3], sigma[4]):.2g} µT (limit {PLANAR_MAX_SIGMA_UT:g}), and "
            "a short arc lets the iron trade with them beyond that: turn the vehicle through at "
            "least half a circle, or use --heading DEG at a known heading")
    A, b = _planar_parts(theta)
    inliers = r2 <= CHI2_2_INLIER * scale ** 2
    fit = ReferenceFit(
        rotation=mount_rotations()[0], A=A, b=b,
        weights=1.0 / (1.0 + r2 / (CAUCHY_C * scale) ** 2), scale=scale,
        rms=float(np.sqrt(np.mean(r2[inliers]))), inliers=inliers,
        held={name: 1.0 for name in VERTICAL_IRON},
        sigma=dict(zip(("A11", "A22", "A12", "bx", "by", "bz"), map(float, sigma))))
    undetermined = {name: ("held at the identity's value: turning in the plane does not "
                           "change the vertical field, so the vertical scale and its cross terms "
                           "cannot be told from the vertical offset" if share >= 1 else
                           f"held near the identity (the data left {share:.0%} of the prior's σ)")
                    for name, share in fit.held.items()}
    undetermined["heading offset"] = ("a rotation about the vertical (a yaw mounting error) is "
                                      "not seen: the headings come from the compass itself")
    undetermined["orientation"] = "assumed NONE (the compass axes are the vehicle's)"
    cal = calibration_from_fit(fit, F, f"planar turns ({len(m)} samples, {arc:.0f}° of "
                                       "heading)", undetermined)
    extra = dict(cal.extra)
    extra["planar"] = {"heading_arc_deg": round(arc, 1),
                       "sigma": {k: round(v, 4) for k, v in fit.sigma.items()},
                       "reference": ref["source"]}
    return cal.replace(method="planar", extra=extra)
