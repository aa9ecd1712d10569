"""The attitude reference: the field a log's own attitude and position say the compass should
have measured, and how far a calibration is from it (ArduPilot MAGFit's view, fitted robustly).

Expected body-frame field of each magnetometer sample ``j``::

    e_j = R_jᵀ · B_NED

``B_NED`` the World Magnetic Model's field (north, east, down; µT) at the log's median GPS
position and date (or ``--lat/--lon/--date``), ``R_j`` the logged attitude (body
forward-right-down → NED; track columns ``att_q*``, interpolated to the sample). A
calibration's body-frame field ``f_j`` is set beside it: the residual ``f_j − e_j`` (µT) and
the heading error, the angle between the horizontal parts of ``R_j f_j`` and ``B_NED`` (its
size is the error a compass heading would have; positive when the measured field points east
of the model's, which makes the compass heading read west of the true one).

"Before" is a calibration in force (the autopilot's, :mod:`streamcal.inputs.autopilot_cal`)
or, without one, the readings as logged; "after" is the robust fit against the reference
(:mod:`.reference_fit`: offsets, symmetric soft iron, interference of the given channels and the
mounting rotation that fits best). Both are compared on the same samples: the inliers of the
fit (robust weight ≥ ½) inside the window where the attitude is sampled.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..calibration import Calibration, canonical_form
from ..constants import ATTITUDE_COLUMNS
from ..geomag import ned_field, parse_date, wmm_field
from ..inputs.autopilot_cal import px4_rotation
from ..inputs.mount_rotations import as_dict
from .reference_fit import ReferenceFit, detect_rotation, fit_reference, residual_rotation_deg

CAVEAT = ("the logged attitude is the autopilot's estimate and its yaw is itself steered by "
          "the compass, so part of a compass error hides in the yaw: heading errors here are a "
          "lower bound; the World Magnetic Model leaves out local anomalies (steel, buildings, "
          "crustal fields)")
#: Fewer samples than this in the window: no reference.
MIN_SAMPLES = 50
#: Eigenvalues of the fitted A (the compass's gain against the model) outside this range
#: mean the readings do not follow the reference at all.
GAIN_RANGE = (0.25, 4.0)
#: Attitudes that turn the expected field by less than this (µT, largest standard deviation
#: along an axis) cannot tell soft iron from offsets, nor a mounting rotation.
MIN_SPREAD_UT = 5.0


@dataclass
class AttitudeData:
    """Magnetometer samples with the logged attitude and the expected field.

    Attributes:
        t: (M,) s; m: (M,3) readings (track unit, µT); q: (M,4) unit quaternions (w,x,y,z)
        body → NED; expected: (M,3) expected body-frame field µT; cov: covariates at the
        samples; ref: the World Magnetic Model figures used (:func:`streamcal.geomag.wmm_field`);
        rows: (M,) indices of these samples among the track's magnetometer samples.
    """

    t: np.ndarray
    m: np.ndarray
    q: np.ndarray
    expected: np.ndarray
    cov: dict
    ref: dict
    rows: np.ndarray

    @property
    def b_ned(self) -> np.ndarray:
        return ned_field(self.ref)


def log_location(track) -> tuple[dict | None, str]:
    """The World Magnetic Model at the track's GPS position and date (metadata ``gps_*``):
    ``(ref, "")`` or ``(None, why not)``."""
    meta = track.metadata
    if "gps_lat_deg" not in meta:
        return None, "the log has no GPS position (give --lat/--lon/--date)"
    date = parse_date(meta["gps_date"]) if meta.get("gps_date") else None
    ref = wmm_field(float(meta["gps_lat_deg"]), float(meta["gps_lon_deg"]),
                    float(meta.get("gps_alt_m", 0.0)) / 1000.0, date)
    if date is None:
        ref["note"] = "the log's GPS gives no date: today's field used"
    return ref, ""


def _rotations(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q_wxyz)[:, [1, 2, 3, 0]])


def attitude_data(track, ref: dict | None = None) -> tuple[AttitudeData | None, str]:
    """The samples the reference covers: ``(data, "")`` or ``(None, why not)``.

    ``ref`` overrides the log's own position (``--lat/--lon``). Samples outside the span of
    the attitude samples (no interpolation there) are left out.
    """
    if not all(track.has(c) for c in ATTITUDE_COLUMNS):
        return None, "the log has no attitude (ArduPilot ATT/AHR2, PX4 vehicle_attitude)"
    if track.mag_unit != "uT":
        return None, f"the readings are in {track.mag_unit}, the reference in µT"
    if ref is None:
        ref, why = log_location(track)
        if ref is None:
            return None, why
    cov = track.covariates_at_mag()
    sampled = ~np.isnan(track.columns[ATTITUDE_COLUMNS[0]])
    t_att = track.t[sampled]
    t = track.t_mag
    rows = np.flatnonzero((t >= t_att[0]) & (t <= t_att[-1]))
    if len(rows) < MIN_SAMPLES:
        return None, (f"only {len(rows)} magnetometer samples while the attitude is logged "
                      f"(need {MIN_SAMPLES})")
    q = np.column_stack([cov[c][rows] for c in ATTITUDE_COLUMNS])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    b_ned = ned_field(ref)
    expected = _rotations(q).inv().apply(b_ned)
    sub = {k: np.asarray(v)[rows] for k, v in cov.items()}
    return AttitudeData(t=t[rows], m=track.mag[rows], q=q, expected=expected, cov=sub,
                        ref=ref, rows=rows), ""


def heading_error_deg(q: np.ndarray, field_body: np.ndarray, b_ned: np.ndarray) -> np.ndarray:
    """(M,) signed angle (degrees, east positive) from the horizontal part of ``b_ned`` to
    that of the body-frame ``field_body`` (M,3) turned to NED by ``q`` (M,4 w,x,y,z)."""
    f = _rotations(q).apply(field_body)
    ang = np.arctan2(f[:, 1], f[:, 0]) - np.arctan2(b_ned[1], b_ned[0])
    return np.degrees((ang + np.pi) % (2 * np.pi) - np.pi)


def body_field(cal: Calibration, m: np.ndarray, cov: dict, meta=None) -> np.ndarray:
    """A calibration's field in the body frame (M,3) µT: ``|B| Qᵀ K⁻¹ (m − b − terms)`` with
    ``Q`` = ``extra["frame_rotation_Q"]`` (the frame an autopilot's or a reference fit's
    calibration was built in: body-frame directions rotated by Q); without it the calibrated
    field is in the frame of the readings, turned into the body frame by PX4's rotation when
    the track's metadata ``meta`` say the readings are ``sensor_mag``'s (:func:`px4_rotation`)."""
    x = cal.apply(m, cov)
    Q = (cal.extra or {}).get("frame_rotation_Q")
    if Q is not None:
        x = x @ np.asarray(Q, float)
    elif (R := px4_rotation(meta or {})) is not None:
        x = x @ R.T
    return (cal.field or cal.radius) * x


def before_field(track, cal: Calibration | None, data: AttitudeData) -> np.ndarray:
    """The body-frame field (M,3) µT of the calibration in force (:func:`body_field`); the
    readings as logged (turned by PX4's rotation when they are ``sensor_mag``'s) when ``cal``
    is None."""
    if cal is not None:
        return body_field(cal, data.m, data.cov, track.metadata)
    R = px4_rotation(track.metadata)
    return data.m if R is None else data.m @ R.T


def calibration_from_fit(fit: ReferenceFit, field_uT: float, source: str,
                         undetermined: dict | None = None) -> Calibration:
    """The fit as a streamcal calibration of the readings as logged:
    ``m = |F| Rᵀ A u + Rᵀ b + Σ Rᵀ g (a − a0)``, ``u`` the body-frame direction;
    ``K Q = |F| Rᵀ A`` (``frame_rotation_Q`` = Q in ``extra``), the mounting rotation in
    ``extra["orientation"]`` when it is not NONE."""
    Rt = fit.rotation.matrix.T
    K, Q = canonical_form(field_uT * Rt @ fit.A)
    model, effects = ["hard_iron", "soft_iron"], {}
    if fit.g:
        model.append("aux_interference")
        effects["aux_interference"] = {"channels": {
            name: {"a0": fit.a0[name], "g": [float(v) for v in Rt @ g]}
            for name, g in fit.g.items()}}
    w = fit.weights
    extra = {"source": source, "frame_rotation_Q": Q.tolist(),
             "note": "fitted against the expected field (World Magnetic Model rotated by the "
                     "logged attitude); calibrated directions are body-frame directions "
                     "rotated by frame_rotation_Q"}
    if fit.rotation.name != "NONE":
        extra["orientation"] = as_dict(fit.rotation, None)
    if undetermined:
        extra["undetermined"] = dict(undetermined)
    inl = fit.inliers if fit.inliers is not None else w >= 0.5
    return Calibration(K=K, b=Rt @ fit.b, model=tuple(model), effects=effects,
                       rms=fit.rms, n=len(w), n_outliers=int(np.sum(~inl)),
                       field=float(field_uT), method="attitude_reference", unit="uT",
                       kernel="cauchy", extra=extra)


def held_parameters(fit: ReferenceFit) -> dict:
    """``{parameter: what was assumed and why}`` for the parameters the prior held."""
    out = {}
    for name, share in fit.held.items():
        centre = "the identity" if name.startswith("A") else "its prior" if name.startswith("b") \
            else "0 per unit"
        out[name] = (f"held at {centre}: the attitudes in the log cannot determine it" if share >= 1
                     else f"held near {centre} (the data left {share:.0%} of the prior's σ): "
                          "the attitudes in the log do not determine it")
    return out


def attitude_spread_uT(expected: np.ndarray) -> float:
    """Largest standard deviation (µT) of the expected body-frame field along any axis: how
    much the attitudes in the window turn the field (0 for a vehicle that never moved)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(np.asarray(expected).T)).max(), 0.0)))


def reference_fit(data: AttitudeData, channels=(), detect: bool = True) -> tuple[ReferenceFit, str]:
    """The robust fit against ``data.expected`` over the interference ``channels`` that the
    samples carry (:func:`.reference_fit.detect_rotation` when ``detect``), and a note.

    When the attitudes hardly turn the field (spread under :data:`MIN_SPREAD_UT`), the iron
    and the offsets cannot be told apart: A is held at the identity, only offsets (and
    channels) are fitted, and no mounting rotation is looked for."""
    chans = {c: data.cov[c] for c in channels if c in data.cov}
    spread = attitude_spread_uT(data.expected)
    if spread < MIN_SPREAD_UT:
        fit = fit_reference(data.m, data.expected, chans, fixed_A=np.eye(3))
        return fit, (f"the attitudes turn the expected field by only {spread:.2g} µT (under "
                     f"{MIN_SPREAD_UT:g}): soft iron held at the identity, mounting not checked")
    if detect:
        return detect_rotation(data.m, data.expected, chans)[0], ""
    return fit_reference(data.m, data.expected, chans), ""


def on_reference_inliers(data: AttitudeData, channels=()) -> AttitudeData:
    """``data`` kept to the samples every heading figure against the attitude is over: the
    inliers of the robust fit against the reference (:func:`reference_fit` over the
    interference ``channels`` the samples carry, no mounting search), so that a disturbance
    counts in no calibration's figure."""
    return reference_inliers(data, channels)[0]


def reference_inliers(data: AttitudeData, channels=()) -> tuple[AttitudeData, ReferenceFit]:
    """:func:`on_reference_inliers` and the fit that chose them."""
    fit = reference_fit(data, channels, detect=False)[0]
    keep = fit.inliers
    return AttitudeData(t=data.t[keep], m=data.m[keep], q=data.q[keep],
                        expected=data.expected[keep],
                        cov={k: np.asarray(v)[keep] for k, v in data.cov.items()},
                        ref=data.ref, rows=data.rows[keep]), fit


def implausible(fit: ReferenceFit) -> str:
    """Why the fit cannot be a calibration (its gains outside :data:`GAIN_RANGE`), or ""."""
    gains = np.linalg.eigvalsh(fit.A)
    if gains.min() >= GAIN_RANGE[0] and gains.max() <= GAIN_RANGE[1]:
        return ""
    return (f"the readings do not follow the attitude reference: the fitted gains against the "
            f"model are {gains.min():.2g}..{gains.max():.2g} (plausible "
            f"{GAIN_RANGE[0]:g}..{GAIN_RANGE[1]:g}); the logged yaw may not come from this "
            "compass, or the place or date is wrong")


def _stats(data: AttitudeData, field: np.ndarray, keep: np.ndarray) -> tuple[float, float, float]:
    res = np.linalg.norm(field[keep] - data.expected[keep], axis=1)
    head = np.abs(heading_error_deg(data.q[keep], field[keep], data.b_ned))
    return (float(np.sqrt(np.mean(res ** 2))), float(np.sqrt(np.mean(head ** 2))),
            float(np.percentile(head, 95)))


def _empty(reason: str) -> dict:
    keys = ("rms_uT_before", "rms_uT_after")
    return {"attitude_reference": {**dict.fromkeys(keys), "heading_error_deg": None,
                                   "window_s": None, "caveat": CAVEAT, "reason": reason},
            "orientation": None}


def attitude_reference(track, cal_before: Calibration | None = None,
                       cal_after: Calibration | None = None, *, ref: dict | None = None,
                       channels=None, detect: bool = True) -> dict:
    """``{"attitude_reference": {...}, "orientation": {...}}`` (docs/flight_logs.md).

    Args:
        track: a track with ``att_q*`` columns and a GPS position (or ``ref``).
        cal_before: the calibration in force (None: the readings as logged).
        cal_after: streamcal's calibration to judge; None fits one against the reference.
        ref: :func:`streamcal.geomag.wmm_field` result overriding the log's position.
        channels: interference channels of the fit (default: those of ``cal_before``'s
            aux_interference that the track has).
        detect: look for a mounting rotation.

    Without attitude or position every number is null and ``reason`` says why; when the fit
    against the reference is no calibration (:func:`implausible`), the "after" numbers and the
    orientation are null, ``reason`` says why, and "before" is on every sample of the window.
    """
    data, why = attitude_data(track, ref)
    if data is None:
        return _empty(why)
    if channels is None:
        aux = dict((cal_before.effects if cal_before else {}).get("aux_interference") or {})
        channels = list(aux.get("channels", {}))
    fit, note = reference_fit(data, channels, detect)
    failed = implausible(fit) if cal_after is None else ""
    keep = fit.inliers if not failed else np.ones(len(data.t), dtype=bool)
    before = before_field(track, cal_before, data)
    rb, hb, pb = _stats(data, before, keep)
    ra = ha = pa = angle = None
    if not failed:
        after_cal = cal_after or calibration_from_fit(fit, data.ref["intensity_uT"],
                                                      "attitude reference fit")
        after = body_field(after_cal, data.m, data.cov, track.metadata)
        ra, ha, pa = _stats(data, after, keep)
        angle = residual_rotation_deg(fit.body_field(data.m, data.cov) if cal_after is None
                                      else after, data.expected, fit.weights)

    def r(v, digits):
        return None if v is None else round(v, digits)

    out = {
        "rms_uT_before": round(rb, 3), "rms_uT_after": r(ra, 3),
        "heading_error_deg": {"rms_before": round(hb, 2), "rms_after": r(ha, 2),
                              "p95_before": round(pb, 2), "p95_after": r(pa, 2)},
        "window_s": [round(float(data.t[0]), 3), round(float(data.t[-1]), 3)],
        "caveat": CAVEAT,
        "n": int(keep.sum()), "n_outliers": int((~keep).sum()),
        "before": (cal_before.extra or {}).get("source", cal_before.method) if cal_before
        else "the readings as logged",
        "after": "streamcal's fit against the reference" if cal_after is None
        else (cal_after.extra or {}).get("source", cal_after.method),
        "reference": {k: data.ref[k] for k in ("source", "lat", "lon", "alt_km", "date",
                                                "intensity_uT", "inclination_deg",
                                                "declination_deg")},
        "undetermined": held_parameters(fit),
    }
    if note:
        out["note"] = note
    if failed:
        out.update(reason=failed, after=None, undetermined={})
    orientation = None if note or failed else {**as_dict(fit.rotation, angle),
                                               **mounting_advice(track.metadata, fit.rotation)}
    return {"attitude_reference": out, "orientation": orientation}


def mounting_advice(meta, found) -> dict:
    """What a mounting rotation ``found`` (relative to the frame of the readings) means for the
    autopilot's parameter: ``{"configured": {"param", "value"}, "set": {"param", "value"}}``.

    The parameter is the compass's (COMPASS_ORIENTn, CAL_MAGn_ROT), or the board's
    (AHRS_ORIENTATION, SENS_BOARD_ROT) for an internal compass
    (:func:`~streamcal.inputs.autopilot_cal.compass_rotation_param`). ArduPilot's MAG and
    PX4's calibrated topics are logged after the configured rotation, so the rotation to set
    is ``found`` after it; PX4's ``sensor_mag`` is the sensor's own frame, so it is ``found``
    itself. ``{}`` when the log names no such parameter; ``"value": None`` when the product is
    not a numbered rotation."""
    from ..inputs.autopilot_cal import compass_rotation_param
    from ..inputs.mount_rotations import by_number, matching

    meta = dict(meta or {})
    try:
        firmware, param = compass_rotation_param(meta) or (None, None)
        if param is None:
            return {}
        configured = max(int(float(meta[f"param.{param}"])), 0)
    except (KeyError, ValueError):
        return {}
    logged_after = firmware == "ardupilot" or meta.get("mag_calibrated_by_px4") == "yes"
    base = by_number(configured, firmware)
    if base is None:
        total = None
    else:
        total = matching(found.matrix @ base.matrix) if logged_after else found
    return {"configured": {"param": param, "value": configured},
            "set": {"param": param, "value": None if total is None else getattr(total, firmware)}}


def log_attitude_reference(track, ref: dict | None = None,
                           calibration: Calibration | None = None) -> dict:
    """:func:`attitude_reference` of a log against the calibration in force in it (the
    autopilot's parameters, else the readings as logged).

    A track without attitude columns gets only ``{"orientation": …}`` from gravity
    (:mod:`.orientation_gravity`) when it has an accelerometer, a place (``ref`` or a GPS
    position) and a ``calibration`` in µT to turn the readings into the field; else ``{}``
    (nothing to add to ``diagnose --json``)."""
    if track is None:
        return {}
    if not all(track.has(c) for c in ATTITUDE_COLUMNS):
        return _gravity_orientation(track, ref, calibration)
    return attitude_reference(track, calibration_in_force(track), ref=ref)


def calibration_in_force(track) -> Calibration | None:
    """The autopilot's calibration in the log's parameters
    (:func:`streamcal.inputs.autopilot_calibration`), None when it has none."""
    from ..errors import InputError
    from ..inputs import autopilot_calibration

    try:
        return autopilot_calibration(track)
    except InputError:
        return None


def reference_series(track, cal_before: Calibration | None = None, *, ref: dict | None = None,
                     channels=()) -> dict | None:
    """The per-sample series behind :func:`attitude_reference` for a figure: ``{"t" (M,),
    "expected", "before", "after" (M,3) µT body frame, "heading_before", "heading_after"
    (M,) degrees, "inliers" (M,) bool, "before_label"}``; None without attitude or position."""
    data, _ = attitude_data(track, ref)
    if data is None:
        return None
    fit, _ = reference_fit(data, channels)
    before = before_field(track, cal_before, data)
    after = fit.body_field(data.m, data.cov)
    return {"t": data.t, "expected": data.expected, "before": before, "after": after,
            "heading_before": heading_error_deg(data.q, before, data.b_ned),
            "heading_after": heading_error_deg(data.q, after, data.b_ned),
            "inliers": fit.inliers,
            "before_label": "calibration in force" if cal_before is not None else "as logged"}


def fit_attitude_reference(track, ref: dict | None = None, channels=()) -> Calibration:
    """The calibration fitted against the attitude reference (offsets, symmetric iron, the
    interference of ``channels``, the mounting rotation): what ``fit LOG --attitude`` saves.
    Raises :class:`~streamcal.errors.InsufficientDataError` saying why there is no reference."""
    from ..errors import InsufficientDataError

    data, why = attitude_data(track, ref)
    if data is None:
        raise InsufficientDataError(f"no attitude reference: {why}")
    fit, note = reference_fit(data, channels)
    failed = implausible(fit)
    if failed:
        raise InsufficientDataError(f"no fit against the attitude reference: {failed}")
    undetermined = held_parameters(fit)
    if note:
        undetermined["orientation"] = f"assumed NONE: {note}"
    cal = calibration_from_fit(fit, data.ref["intensity_uT"],
                               f"attitude reference ({data.ref['source']} at the log's position, "
                               f"logged attitude, {len(data.t)} samples)", undetermined)
    extra = dict(cal.extra)
    advice = mounting_advice(track.metadata, fit.rotation)
    if fit.rotation.name != "NONE":
        extra["orientation"] = {**as_dict(fit.rotation, residual_rotation_deg(
            fit.body_field(data.m, data.cov), data.expected, fit.weights)), **advice}
    return cal.replace(extra=extra)


def _gravity_orientation(track, ref, calibration) -> dict:
    from .orientation_gravity import orientation_from_gravity

    if calibration is None or calibration.unit != "uT" or not track.has("accel") \
            or track.mag_unit != "uT":
        return {}
    if ref is None:
        ref, _ = log_location(track)
        if ref is None:
            return {}
    cov = track.covariates_at_mag()
    a = np.column_stack([cov[c] for c in ("ax", "ay", "az")])
    down = -a / np.linalg.norm(a, axis=1, keepdims=True)
    field = body_field(calibration, track.mag, cov)
    return {"orientation": orientation_from_gravity(field, down, ref["inclination_deg"])}
