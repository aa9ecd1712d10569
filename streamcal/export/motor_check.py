"""A motor compensation checked the way a user would load it, on samples it was not fitted on:
the other part of the same flight (:func:`held_out_check`) or another flight of the same
vehicle (:func:`flight_check`, ``streamcal check CAL FLIGHT``).

A flight is split in time: the first part refines the calibration in force with a motor term on
one channel (``fit FLIGHT --cal autopilot --add aux_interference=CHANNEL``), the term is
exported as each firmware's parameters (ArduPilot ``COMPASS_MOT_*``/``COMPASS_MOTCT``, PX4
``CAL_MAG0_*COMP``/``CAL_MAG_COMP_TYP``), and each firmware's own correction formula
(:func:`.ardupilot.apply_ardupilot`, :func:`.px4.apply_px4`) is applied to the raw readings of
the other part. "Before" is the calibration in force exported and applied the same way.

Figures on the held-out part:

* field-magnitude spread: standard deviation of ``|f|`` over its mean (%), every sample, and
  its robust form (1.4826 × median absolute deviation over the median) that the log's bursts
  do not dominate;
* heading error against the attitude reference (the World Magnetic Model rotated by the logged
  attitude, :mod:`streamcal.fitting.attitude_reference`) where the log has attitude and a
  position: rms and 95th percentile (degrees) over the samples inside the attitude's span that
  the robust fit against the reference keeps (``on_reference_inliers``, the samples of every
  heading figure), with that module's caveat (the logged yaw is itself steered by the compass).
"""
from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ..constants import MAD_TO_SIGMA
from ..diagnosis.against import refine
from ..errors import InputError
from ..fitting.attitude_reference import (attitude_data, body_field, heading_error_deg,
                                          log_location, on_reference_inliers)
from ..fitting.heading_check import WORSE_DEG, WORSE_FRACTION
from ..inputs.autopilot_cal import MOTOR_AFTER_MATRIX, UT_PER_GAUSS, px4_rotation
from ..inputs.autopilot_cal import PX4_KA_PER_A as KA_PER_A
from .ardupilot import MG_PER_UT, apply_ardupilot
from .ardupilot import export as export_ardupilot
from .common import CURRENT_CHANNELS, THROTTLE_CHANNELS, motor_channel, mounting
from .px4 import apply_px4
from .px4 import export as export_px4

FIRMWARES = ("ardupilot", "px4")
#: A change of the field-magnitude spread counts when it exceeds this (percentage points) and
#: :data:`WORSE_FRACTION` of the spread before; the heading's counts as in
#: :mod:`streamcal.fitting.heading_check` (:data:`WORSE_DEG`, :data:`WORSE_FRACTION`).
SPREAD_PP = 0.1


def split_in_time(track, fraction: float = 0.5) -> tuple:
    """(first, rest): the rows before and from the magnetometer time that splits its samples
    ``fraction`` : ``1 − fraction``."""
    if not 0.0 < fraction < 1.0:
        raise InputError(f"the fitted part must be a fraction in (0, 1), got {fraction}")
    t_split = float(np.quantile(track.t_mag, fraction))
    first = track.t < t_split
    return track.select(first), track.select(~first)


def read_parameters(text: str, firmware: str) -> dict:
    """``{name: value}`` of an exported parameter file (:func:`streamcal.export.export` text)."""
    out = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, value = line.split(",") if firmware == "ardupilot" else line.split("\t")[2:4]
        out[name] = float(value)
    return out


def firmware_field(cal: Calibration, firmware: str, m_uT: np.ndarray,
                   signal: np.ndarray | None, ardupilot_order: str = MOTOR_AFTER_MATRIX,
                   meta=None) -> np.ndarray:
    """``cal`` exported for ``firmware`` and applied with its formula to readings ``m_uT``
    (M,3) µT with the motor channel's values ``signal`` (M,) (throttle 0..1 or current A):
    the corrected field (M,3) in µT in the body frame, as the firmware turns it there;
    ArduPilot's motor term written and added in ``ardupilot_order``. A calibration fitted for
    another compass than the first is exported under the first's parameter names: the formula
    is the same for every parameter set.

    The frame: ArduPilot rotates a reading by the COMPASS_ORIENT the export writes (a mounting
    rotation ``cal`` found) before its formula; PX4 turns its formula's output by the
    CAL_MAGn_ROT the export writes, else by the one configured in the log when the readings
    are ``sensor_mag``'s (:func:`~streamcal.inputs.autopilot_cal.px4_rotation` of the
    track's metadata ``meta``); otherwise the readings' frame is the body frame."""
    extra = dict(cal.extra or {})
    if extra.pop("compass_params_index", 0):
        cal = cal.replace(extra=extra)
    written = mounting(cal, firmware)[0]
    turn = px4_rotation(meta or {}) if written is None else written
    if firmware == "ardupilot":
        if written is not None:
            m_uT, turn = m_uT @ written.T, None
        params = read_parameters(export_ardupilot(cal, order=ardupilot_order)[0], firmware)
        field = apply_ardupilot(params, MG_PER_UT * m_uT, signal, ardupilot_order) / MG_PER_UT
    else:
        params = read_parameters(export_px4(cal)[0], firmware)
        power = None
        if signal is not None and params.get("CAL_MAG_COMP_TYP"):
            power = signal * (KA_PER_A if params["CAL_MAG_COMP_TYP"] >= 2 else 1.0)
        field = apply_px4(params, m_uT / UT_PER_GAUSS, power) * UT_PER_GAUSS
    return field if turn is None else field @ turn.T


def _spread(field: np.ndarray) -> dict:
    norm = np.linalg.norm(field, axis=1)
    med = np.median(norm)
    return {"spread_pct": round(float(100.0 * np.std(norm) / np.mean(norm)), 3),
            "spread_robust_pct": round(float(100.0 * MAD_TO_SIGMA
                                             * np.median(np.abs(norm - med)) / med), 3)}


def _heading(field: np.ndarray, data) -> dict:
    head = np.abs(heading_error_deg(data.q, field, data.b_ned))
    return {"heading_rms_deg": round(float(np.sqrt(np.mean(head ** 2))), 3),
            "heading_p95_deg": round(float(np.percentile(head, 95)), 3)}


def held_out_check(track, cal_in_force: Calibration, channel: str, *, fraction: float = 0.5,
                   fit_on: str = "first", ref: dict | None = None,
                   source: str = "autopilot calibration in force") -> dict:
    """Fit a motor term on ``channel`` over the first ``fraction`` of ``track`` (µT), check it on
    the rest with each firmware's formula; ``fit_on="last"`` fits on the rest and checks on
    the first part.

    Three calibrations are set side by side on the held-out part: ``before`` (``cal_in_force``),
    ``refit`` (refined on the fitted part without a motor term: what the refit alone changes)
    and ``after`` (refined with it); each ``{firmware: figures}``, plus ``streamcal`` (the
    ``after`` calibration's own correction). Figures: ``spread_pct`` and
    ``spread_robust_pct`` over every held-out sample; ``heading_rms_deg``, ``heading_p95_deg``
    against the attitude reference over the held-out samples inside the attitude's span that
    the reference fit keeps, when
    the track has attitude and a position (``ref`` or its GPS), else ``heading`` says why not.
    ArduPilot's formula adds the motor term in the order of the firmware ``cal_in_force`` came
    from (``extra["ardupilot_correction_order"]``; the newest when absent).
    ``compare``: :func:`compare` of each firmware's ``before`` and ``after``. Also
    ``channel``, ``fit_on``, ``fitted_s``, ``checked_s``, ``n_checked``, ``n_heading``
    (the checked samples with a heading error), ``g_uT`` (the fitted term, µT per channel
    unit). InputError
    when the channel is not a throttle or battery current the firmwares take, or the track
    lacks it, or the calibration in force compensates another channel. A motor term in force
    on ``channel`` is held by ``refit`` and fitted afresh by ``after``.
    """
    if channel not in CURRENT_CHANNELS + THROTTLE_CHANNELS:
        raise InputError(f"motor compensation check: {channel!r} is neither a throttle "
                         f"({', '.join(THROTTLE_CHANNELS)}) nor a battery current "
                         f"({', '.join(CURRENT_CHANNELS)})")
    if channel not in track.aux_names:
        raise InputError(f"motor compensation check: the track has no channel {channel!r} "
                         f"(channels: {', '.join(track.aux_names) or 'none'})")
    in_force = needed_channels(cal_in_force)
    if any(c != channel for c in in_force):
        raise InputError(f"motor compensation check: the calibration in force compensates "
                         f"{', '.join(in_force)}; check that channel, not {channel!r}")
    if ref is None:
        ref, why = log_location(track)
    if fit_on not in ("first", "last"):
        raise InputError(f"motor compensation check: fit_on is 'first' or 'last', not {fit_on!r}")
    fit_part, check_part = split_in_time(track.keep_aux([channel]), fraction)
    if fit_on == "last":
        fit_part, check_part = check_part, fit_part
    cals = {"before": cal_in_force,
            "refit": refine(fit_part, cal_in_force, [], calibration_source=source, location=ref),
            "after": refine(fit_part, cal_in_force, ["aux_interference"],
                            calibration_source=source, location=ref)}
    m = np.asarray(check_part.mag, dtype=float)
    meta = check_part.metadata
    signal = np.asarray(check_part.covariates_at_mag()[channel], dtype=float)
    data, why = attitude_data(check_part, ref) if ref is not None else (None, why)
    if data is not None:
        data = on_reference_inliers(data, needed_channels(cal_in_force))
    out = {"channel": channel, "fit_on": fit_on,
           "fitted_s": [round(float(fit_part.t_mag[0]), 3), round(float(fit_part.t_mag[-1]), 3)],
           "checked_s": [round(float(check_part.t_mag[0]), 3),
                         round(float(check_part.t_mag[-1]), 3)],
           "n_checked": int(len(m)),
           "n_heading": int(len(data.rows)) if data is not None else 0,
           "g_uT": [float(v) for v in
                    cals["after"].effects["aux_interference"]["channels"][channel]["g"]]}
    if data is None:
        out["heading"] = f"no heading error: {why}"

    order = (cal_in_force.extra or {}).get("ardupilot_correction_order", MOTOR_AFTER_MATRIX)
    for name, cal in cals.items():
        out[name] = {fw: figures(firmware_field(cal, fw, m, signal, order, meta), data)
                     for fw in FIRMWARES}
    out["streamcal"] = figures(body_field(cals["after"], m, {channel: signal}, meta), data)
    out["compare"] = {fw: compare(out["before"][fw], out["after"][fw]) for fw in FIRMWARES}
    return out


def figures(field: np.ndarray, data) -> dict:
    """Spread figures of ``field`` (M,3) µT over every sample, heading figures over the
    samples of ``data`` (:class:`~streamcal.fitting.attitude_reference.AttitudeData` of the
    same samples, or None: no heading figures)."""
    return {**_spread(field), **(_heading(field[data.rows], data) if data is not None else {})}


def motor_signal(cal: Calibration, firmware: str, cov: dict) -> np.ndarray | None:
    """(M,) values of the channel ``firmware``'s motor compensation takes from ``cal``'s
    ``aux_interference`` term (:func:`.common.motor_channel`), None when it takes none."""
    chosen = motor_channel(needed_channels(cal), second_battery=firmware == "px4")[0]
    return None if chosen is None else np.asarray(cov[chosen], dtype=float)


def needed_channels(cal: Calibration) -> list[str]:
    """The auxiliary channels ``cal``'s ``aux_interference`` term reads."""
    return list(((cal.effects or {}).get("aux_interference") or {}).get("channels", {}))


def flight_check(track, cal: Calibration, cal_in_force: Calibration | None, *,
                 ref: dict | None = None) -> dict:
    """``cal`` on every magnetometer sample of ``track`` (µT; a flight it was not fitted on)
    beside ``cal_in_force`` (the calibration in the log's parameters; None: the readings as
    logged).

    Returns ``{"n", "n_heading", "channels", "before", "after", "compare"}``: ``before``
    ``{firmware: figures}`` of ``cal_in_force`` exported and applied with each firmware's
    formula, or ``{"logged": figures}`` of the readings; ``after`` the same of ``cal`` plus
    ``"streamcal"`` (its own correction, every covariate at its value); ``channels``
    ``{firmware: the motor channel its formula takes, or None}``; figures as in
    :func:`held_out_check`, ``compare`` :func:`compare` of each firmware's pair. Without a
    heading figure (no attitude or place: ``ref``, else the log's GPS) ``heading`` says why and
    ``n_heading`` is 0. InputError when ``track`` lacks a channel either calibration reads."""
    cov = track.covariates_at_mag()
    for which, c in (("the calibration", cal), ("the calibration in force", cal_in_force)):
        lacking = [name for name in needed_channels(c) if name not in cov] if c else []
        if lacking:
            raise InputError(f"{which} needs channel {', '.join(lacking)} (its motor term), "
                             f"which the recording lacks (channels: "
                             f"{', '.join(track.aux_names) or 'none'})")
    m, meta = np.asarray(track.mag, dtype=float), track.metadata
    order = meta.get("ardupilot_correction_order", MOTOR_AFTER_MATRIX)
    if ref is None:
        ref, why = log_location(track)
    data, why = attitude_data(track, ref) if ref is not None else (None, why)
    if data is not None:
        data = on_reference_inliers(data, needed_channels(cal_in_force) if cal_in_force else ())
    out = {"n": int(len(m)), "n_heading": int(len(data.rows)) if data is not None else 0,
           "channels": {fw: motor_channel(needed_channels(cal), second_battery=fw == "px4")[0]
                        for fw in FIRMWARES}}
    if data is None:
        out["heading"] = f"no heading error: {why}"
    if cal_in_force is None:
        out["before"] = {"logged": figures(m, data)}
    else:
        out["before"] = {fw: figures(firmware_field(cal_in_force, fw, m,
                                                    motor_signal(cal_in_force, fw, cov), order,
                                                    meta), data) for fw in FIRMWARES}
    out["after"] = {fw: figures(firmware_field(cal, fw, m, motor_signal(cal, fw, cov), order,
                                               meta), data) for fw in FIRMWARES}
    out["after"]["streamcal"] = figures(body_field(cal, m, cov, meta), data)
    out["compare"] = {fw: compare(out["before"].get(fw, out["before"].get("logged")),
                                  out["after"][fw]) for fw in FIRMWARES}
    return out


def compare(before: dict, after: dict) -> dict:
    """How ``after``'s figures stand against ``before``'s: ``{"spread", "heading"}`` each
    ``"lower"``, ``"higher"`` or ``"same"`` (within the tolerance, :data:`SPREAD_PP` /
    :data:`WORSE_DEG`, and :data:`WORSE_FRACTION` of the value before; heading None without
    heading figures), ``"worse"`` (either higher), ``"better"`` (one lower, none higher) and
    ``"rule"`` in words."""
    def change(key: str, floor: float):
        if key not in before or key not in after:
            return None
        tol = max(floor, WORSE_FRACTION * before[key])
        return ("lower" if after[key] < before[key] - tol else
                "higher" if after[key] > before[key] + tol else "same")

    out = {"spread": change("spread_pct", SPREAD_PP),
           "heading": change("heading_rms_deg", WORSE_DEG)}
    moves = [v for v in out.values() if v is not None]
    out["worse"] = "higher" in moves
    out["better"] = "lower" in moves and not out["worse"]
    out["rule"] = (f"a figure changes when it moves by more than {SPREAD_PP:g} percentage point "
                   f"(spread) or {WORSE_DEG:g}° (heading rms) and {100 * WORSE_FRACTION:g} % "
                   f"of its value before")
    return out
