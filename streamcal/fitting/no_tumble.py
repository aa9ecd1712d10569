"""Calibration of a vehicle that cannot be tumbled, against the World Magnetic Model.

* **Known heading** (:func:`fit_heading`): a few still seconds at a known true heading (with a
  gyro, only the samples turning slower than ``STILL_RATE`` count). The
  accelerometer gives roll and pitch (gravity), the heading gives yaw, the model the field:
  the expected body-frame field ``e`` is known, and one attitude gives three equations —
  the offset ``b = median(m) − A e`` with the iron ``A`` held (a given calibration's, else the
  identity at the model's field strength).
* **Planar** (:func:`fit_planar`): a rover or boat turning in the plane. Roll and pitch come
  from the accelerometer; the yaw of each sample is taken from the tilt-compensated heading of
  the current calibration, and the robust reference fit (:mod:`.reference_fit`) is repeated:
  the horizontal circle gives the horizontal offsets and iron, the model's vertical component
  (total field and inclination) the vertical offset. A fit against headings from the data
  cannot see a rotation about the vertical; the vertical scale and its cross terms are held
  at the prior (identity) because turning in the plane does not change the vertical field.

Each result lists what it could not determine in ``extra["undetermined"]``
(``{"PARAM": "the value assumed and why"}``).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..calibration import Calibration
from ..constants import STILL_RATE
from ..errors import InsufficientDataError
from ..geomag import ned_field
from .attitude_reference import calibration_from_fit
from .reference_fit import ReferenceFit, fit_reference
from .mount_rotations import mount_rotations

#: Rounds of (headings from the calibration → reference fit) in the planar fit.
PLANAR_ROUNDS = 12
#: Entries of the iron a vehicle turning in the plane cannot see (held at the identity).
VERTICAL_IRON = ("A33", "A13", "A23")
#: Median and 99.9 % point of a χ² with 2 degrees of freedom.
CHI2_2_MEDIAN, CHI2_2_INLIER = 1.3863, 13.816
#: Fewest magnetometer samples with an accelerometer sample for either fit.
MIN_SAMPLES = 10


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


def _headings(fit: ReferenceFit, m: np.ndarray, down: np.ndarray, b_ned: np.ndarray) -> np.ndarray:
    """Yaw (degrees) of each sample: the tilt-compensated heading of the fit's calibrated
    field, turned so that its horizontal part points where the model's does."""
    f = fit.body_field(m)
    level = tilt_rotation(down, 0.0).apply(f)         # body → a level frame with yaw 0
    return np.degrees(np.arctan2(b_ned[1], b_ned[0]) - np.arctan2(level[:, 1], level[:, 0]))


def fit_planar(track, ref: dict) -> Calibration:
    """Offsets and horizontal iron of a vehicle turning in the plane (module docstring)."""
    m, down = _mag_and_down(track)
    b_ned = ned_field(ref)
    F = ref["intensity_uT"]
    # start: offsets at the middle of the readings' horizontal extent, no iron
    fit = ReferenceFit(rotation=mount_rotations()[0], A=np.eye(3),
                       b=(np.percentile(m, 97.5, axis=0) + np.percentile(m, 2.5, axis=0)) / 2)
    fit.b[2] = np.median(m[:, 2]) - b_ned[2]
    for _ in range(PLANAR_ROUNDS):
        yaw = _headings(fit, m, down, b_ned)
        e = tilt_rotation(down, yaw).inv().apply(b_ned)
        fit = fit_reference(m, e, b0=fit.b, weights=fit.weights, hold=VERTICAL_IRON)
    # the headings come from the data, so the horizontal residual along the circle is zero:
    # the residual has two degrees of freedom (radial, vertical), and the inliers follow χ²₂
    r2 = np.sum((fit.body_field(m) @ fit.A.T - e) ** 2, axis=1)
    scale2 = np.median(r2) / CHI2_2_MEDIAN
    fit.inliers = r2 <= CHI2_2_INLIER * scale2
    fit.rms = float(np.sqrt(np.mean(r2[fit.inliers])))
    undetermined = {name: ("held at the identity's value: turning in the plane does not "
                           "change the vertical field, so the vertical scale and its cross terms "
                           "cannot be told from the vertical offset" if share >= 1 else
                           f"held near the identity (the data left {share:.0%} of the prior's σ)")
                    for name, share in fit.held.items()}
    undetermined["heading offset"] = ("a rotation about the vertical (a yaw mounting error) is "
                                      "not seen: the headings come from the compass itself")
    undetermined["orientation"] = "assumed NONE (the compass axes are the vehicle's)"
    cal = calibration_from_fit(fit, F, f"planar turns ({len(m)} samples)", undetermined)
    return cal.replace(method="planar")
