"""``streamcal fit TRACK``: batch calibration (docs/cli.md)."""
from __future__ import annotations

import json
import sys

import numpy as np

from ..calibration import DEFAULT_MODEL, jsonable
from ..model.catalog import EFFECT_NAMES
from ._common import RECORDING_HELP, add_input_options, read_track, recording_argv
from ._location import add_location_options, location_reference
from ._output import check_output, messages_to


def register(sub) -> None:
    p = sub.add_parser("fit", help="calibrate from a recorded track",
                       description="Fit the sensor model to a recorded track (two-stage robust "
                                   "autocalibration by default) and print or save the calibration "
                                   "(docs/calibration_file.md). Exit code 1 when the directions "
                                   "seen leave the model undetermined.")
    p.add_argument("track", help=RECORDING_HELP)
    add_input_options(p, skip_bad_rows=True)
    p.add_argument("--sensor", choices=("mag", "accel"), default="mag")
    p.add_argument("--model", default=",".join(DEFAULT_MODEL),
                   help="comma-separated effects (default: %(default)s); known: "
                        + ", ".join(EFFECT_NAMES) + " (docs/effects.md)")
    p.add_argument("--add", action="append", default=[], metavar="EFFECT",
                   help="add an effect to the model (repeatable; same names as --model); "
                        "aux_interference takes every auxiliary channel, "
                        "aux_interference=CHANNEL only the channels named (repeatable), e.g. "
                        "the one an autopilot's motor compensation takes")
    p.add_argument("--kernel", choices=("auto", "cauchy", "huber", "l1", "gm", "l2"), default="auto",
                   help="robust kernel (default: auto = Cauchy, then a Geman–McClure polish)")
    p.add_argument("--method", default="autocal",
                   help="autocal (default), l1_ellipsoid, l2_ellipsoid, magical, dorveaux, "
                        "vasconcelos, kok_schon, sphere_stream")
    p.add_argument("--tau", default=None,
                   help="kernel width in sensor units, or 'paper' for √3 (default: from the data)")
    p.add_argument("-o", "--output", metavar="CAL.json",
                   help="write the calibration file (atomic; - for stdout, the messages then "
                        "go to stderr)")
    p.add_argument("--json", action="store_true", help="print the calibration as one JSON object")
    p.add_argument("--initial", metavar="CAL", help="warm start from this calibration (JSON "
                   "file or state dir): the LM starts from its K and b")
    p.add_argument("--cal", metavar="CAL", help="refine this calibration (JSON file, state "
                   "dir, 'autopilot'/'log': the one in the log's parameters, or 'default': the "
                   "stated default a diagnosis without a calibration holds) on a recording that "
                   "covers only a slice of the sphere: what the recording determines is "
                   "re-estimated, the rest held, and each --add effect fitted (what `diagnose "
                   "--cal` recommends); --model is then the calibration's")
    p.add_argument("--no-coverage-check", action="store_true",
                   help="fit even when the directions seen leave the model undetermined")
    g = p.add_argument_group("calibration without a tumble (World Magnetic Model as the "
                             "reference; docs/flight_logs.md)")
    how = g.add_mutually_exclusive_group()
    how.add_argument("--heading", type=float, metavar="DEG",
                     help="the track is a few still seconds at this true heading (degrees "
                          "clockwise from true north): solve the offsets, hold the iron "
                          "(--initial's, else none)")
    how.add_argument("--planar", action="store_true",
                     help="the track is a rover or boat turning in the plane: horizontal "
                          "offsets and iron from the turns, the vertical offset from the "
                          "model's inclination and total field")
    how.add_argument("--attitude", action="store_true",
                     help="fit against the log's attitude: the model field at its GPS position "
                          "rotated by the logged attitude (offsets, iron, the compass's mounting "
                          "rotation; with --add aux_interference[=CHANNEL] a motor term on the "
                          "battery current, else the throttle, or CHANNEL)")
    add_location_options(p)
    p.set_defaults(func=run)


def _tau(value):
    if value is None or value == "paper":
        return value
    from ..errors import InputError

    try:
        tau = float(value)
    except ValueError:
        raise InputError(f"--tau: expected a number or 'paper', got {value!r}") from None
    if not np.isfinite(tau) or tau <= 0:
        raise InputError(f"--tau: must be a positive number, got {value!r}")
    return tau


#: The channel ``fit --attitude --add aux_interference`` takes when none is named: the first
#: of these the track has (the signals the autopilots compensate).
MOTOR_SIGNALS = ("battery_current_a", "throttle")


def _motor_channels(args, track) -> list[str]:
    """The channels of ``--add aux_interference[=NAME]`` for ``--attitude`` (InputError for
    another effect or a channel the track lacks)."""
    from ..errors import InputError

    out = []
    for item in args.add:
        name, _, channel = item.partition("=")
        if name != "aux_interference":
            raise InputError(f"--attitude fits offsets, iron and aux_interference; --add {item} "
                             "is not one of them")
        if not channel:
            channel = next((c for c in MOTOR_SIGNALS if track.has(c)), None)
            if channel is None:
                raise InputError("--add aux_interference: the track has neither "
                                 f"{' nor '.join(MOTOR_SIGNALS)}; name a channel "
                                 f"(aux_interference=NAME) of: {', '.join(track.aux_names) or 'none'}")
        elif not track.has(channel):
            raise InputError(f"--add aux_interference={channel}: no such channel in the track "
                             f"(channels: {', '.join(track.aux_names) or 'none'})")
        out.append(channel)
    return out


def _named_channels(args, track):
    """(track, --add effects): ``--add aux_interference=CHANNEL`` (repeatable) keeps only the
    channels named for the aux_interference term (InputError for a channel the track lacks, or
    beside a bare ``--add aux_interference``, which takes them all)."""
    from ..errors import InputError

    named, add = [], []
    for item in args.add:
        name, eq, channel = item.partition("=")
        if not eq or name != "aux_interference":
            add.append(item)
            continue
        if channel not in track.aux_names:
            raise InputError(f"--add aux_interference={channel}: no such channel in the track "
                             f"(channels: {', '.join(track.aux_names) or 'none'})")
        named.append(channel)
    if not named:
        return track, add
    if "aux_interference" in add:
        raise InputError("--add aux_interference takes every auxiliary channel, "
                         "aux_interference=CHANNEL only those named: give one or the other")
    return track.keep_aux(named), add + ["aux_interference"]


def _no_tumble(args, track, initial, ref):
    """The calibration of ``--heading`` / ``--planar`` against the model field ``ref`` at
    ``--lat/--lon/--date``, else at the log's GPS position."""
    from ..errors import InputError
    from ..fitting.attitude_reference import log_location
    from ..fitting.no_tumble import fit_heading, fit_planar

    if args.sensor != "mag":
        raise InputError("--heading, --planar and --attitude calibrate the magnetometer "
                         "(--sensor mag)")
    if (args.add and not args.attitude) or args.model != ",".join(DEFAULT_MODEL):
        raise InputError("--heading and --planar fit offsets and iron, --attitude also "
                         "--add aux_interference[=CHANNEL]; --model and other --add do not apply")
    if ref is None and not args.attitude:
        ref, why = log_location(track)
        if ref is None:
            option = "--planar" if args.planar else "--heading"
            raise InputError(f"{option} needs the place of the recording: {why}")
    if args.planar:
        return fit_planar(track, ref)
    if args.attitude:
        from ..fitting.attitude_reference import fit_attitude_reference

        return fit_attitude_reference(track, ref, _motor_channels(args, track))
    return fit_heading(track, args.heading, ref, initial)


def run(args) -> int:
    from ..errors import InsufficientDataError
    from ..fitting import fit
    check_output(args.output)
    from ._calarg import follow_fitted_compass

    follow_fitted_compass(args)
    ref = location_reference(args)     # a mistyped --lat/--date said before the reading
    track = read_track(args)
    if not (args.planar or args.attitude or args.heading is not None):
        track, args.add = _named_channels(args, track)
    if getattr(args, "cal", None):
        if args.planar or args.attitude or args.heading is not None:
            from ..errors import InputError

            raise InputError("--cal refines a given calibration; --heading, --planar and "
                             "--attitude fit one against the World Magnetic Model: one or the "
                             "other")
        return _refine(args, track, ref)
    initial = None
    if getattr(args, "initial", None):
        from ._calarg import load_calibration_arg

        initial, _ = load_calibration_arg(args.initial, "--initial")
    if args.planar or args.attitude or args.heading is not None:
        cal = _no_tumble(args, track, initial, ref)
    else:
        try:
            cal = fit(track, sensor=args.sensor, model=args.model, add=args.add,
                      kernel=args.kernel, method=args.method, tau=_tau(args.tau),
                      check_coverage=not args.no_coverage_check, initial=initial)
        except InsufficientDataError as exc:
            if "of the sphere" not in str(exc):
                raise
            raise InsufficientDataError(
                f"{exc} A vehicle that cannot be tumbled: --planar for one turning in the plane, "
                "--heading DEG for a few still seconds at a known heading (with --lat/--lon/"
                "--date or a GPS in the log).") from None
    cal = _for_compass(cal, track)
    if args.output:
        cal.save(args.output)
    residual, sensor = "sensor", None
    if args.sensor == "mag":
        from ..diagnosis.scales import calibration_residual, sensor_rms

        residual = calibration_residual(cal)
        if residual != "sensor":   # the tied fit's rms is not on the sensor residual
            sensor = sensor_rms(cal, track)
    say = messages_to(args.output)
    if args.json:
        out = cal.to_dict()
        if sensor is not None:
            out["rms_sensor"] = sensor
        print(json.dumps(jsonable(out), allow_nan=False), file=say)
    else:
        print(format_calibration(cal, args.track, residual, sensor), file=say)
        if args.output:
            print(f"written: {args.output}", file=say)
    return 0


def _for_compass(cal, track):
    """``cal`` marked with the autopilot compass it was fitted for (its parameter set), so that
    ``export`` writes that compass's parameter names."""
    from ..inputs.autopilot_cal import compass_slot

    slot = compass_slot(track.metadata)
    return cal.replace(extra={**dict(cal.extra or {}), **slot}) if slot else cal


def _refine(args, track, ref) -> int:
    """``fit TRACK --cal CAL [--add EFFECT …]``: :func:`streamcal.diagnosis.against.refine`."""
    from ..diagnosis.against import refine
    from ..errors import InputError
    from ._calarg import calibration_for

    if args.sensor != "mag" or args.method != "autocal" or args.initial:
        raise InputError("--cal refines a magnetometer calibration with the held fit: it takes "
                         "neither --sensor accel, --method nor --initial")
    from pathlib import Path

    if args.cal == "default" and not Path(args.cal).exists():
        given, source = None, None   # the stated default a diagnosis without --cal holds
    else:
        given, source = calibration_for(args.cal, track)
    cal = _for_compass(refine(track, given, args.add, calibration_source=source, location=ref),
                       track)
    check = _heading_check(track, given, cal, ref)
    if check:
        cal = cal.replace(extra={**dict(cal.extra or {}), "heading_check": check})
    if args.output:
        cal.save(args.output)
    if check.get("worse"):
        print(f"warning: against the attitude reference the refined calibration points the "
              f"compass worse than {source or 'the given one'}: heading error rms "
              f"{check['rms_before']:.2f}° → {check['rms_after']:.2f}° ({check['rule']}). This "
              f"recording fixes the field's magnitude, not its direction; `streamcal fit "
              f"{' '.join(recording_argv(args))} --attitude` fits against the reference instead",
              file=sys.stderr)
    if args.json:
        print(json.dumps(jsonable(cal.to_dict()), allow_nan=False))
        return 0
    print(format_calibration(cal, args.track))
    held = (cal.extra or {}).get("held") or []
    print(f"  held      {', '.join(held) or 'none'} (at the values of "
          f"{source or 'the stated default'}: this recording cannot determine them)")
    used = (cal.extra or {}).get("attitude_reference_used")
    if used:
        print(f"  attitude  fitted with the field's direction against the attitude reference too "
              f"({used['samples']} samples, width {used['width_deg']:.2g}°); caveat: "
              f"{used['caveat']}")
    if "rms_after" in check:
        print(f"  heading   error rms against the attitude reference (the model field rotated "
              f"by the logged attitude, {check['n']} samples): {check['rms_before']:.2f}° with "
              f"{source or 'the stated default'} → {check['rms_after']:.2f}° refined (p95 "
              f"{check['p95_before']:.2f}° → {check['p95_after']:.2f}°)")
    if args.output:
        print(f"written: {args.output}")
    return 0


def _heading_check(track, given, refined, ref) -> dict:
    """:func:`streamcal.fitting.heading_check.heading_check` of a refinement when the log has
    an attitude (the place: ``ref`` from --lat/--lon, else its GPS); {} without an attitude or
    a given calibration, ``{"reason": …}`` when there is no place."""
    from ..constants import ATTITUDE_COLUMNS
    from ..fitting.heading_check import heading_check

    if given is None or not all(track.has(c) for c in ATTITUDE_COLUMNS):
        return {}
    return heading_check(track, given, refined, ref)


def format_calibration(cal, source: str = "", residual: str = "sensor",
                       sensor_rms: float | None = None) -> str:
    """A human-readable summary of a calibration (units named; the rms names its residual, and
    a tied fit also gives its rms on the sensor residual, ``sensor_rms``)."""
    from ..diagnosis.diagnosis import RESIDUAL_LABELS
    from ..units import display_unit, effect_params

    u = display_unit(cal.unit)
    unit = f" {u}" if u else ""       # an unknown unit is said once, in the first line
    rows = [f"calibration of {cal.sensor} from {source} ({cal.method}"
            + (f", {cal.kernel} kernel" if cal.kernel else "") + ")"
            + ("" if u else "; unit unknown (the recording does not name one streamcal knows)"),
            f"  model     {', '.join(cal.model)}",
            "  K" + (f" [{u}]" if u else "")
            + "".join(f"\n    {row[0]:10.4f} {row[1]:10.4f} {row[2]:10.4f}" for row in cal.K),
            f"  b {f'[{u}]' if u else '':<4}  {cal.b[0]:10.4f} {cal.b[1]:10.4f} {cal.b[2]:10.4f}"]
    for name, params in cal.effects.items():
        rows.append(f"  {name}: {effect_params(name, params, cal.unit)}")
    rows.append(f"  rms       {cal.rms:.4g}{unit} on the {RESIDUAL_LABELS.get(residual, residual)} "
                f"residual over {cal.n - cal.n_outliers} inliers "
                f"({cal.n_outliers} outliers of {cal.n})")
    if sensor_rms is not None:
        rows.append(f"  rms       {sensor_rms:.4g}{unit} on the sensor residual (every direction "
                    f"free; the {RESIDUAL_LABELS.get(residual, residual)} one includes the "
                    f"reference's own error)")
    if cal.coverage is not None:
        rows.append(f"  coverage  {cal.coverage:.0%} of the sphere")
    if cal.field:
        rows.append(f"  field     {cal.field:.4g}{unit}")
    for name, why in dict((cal.extra or {}).get("undetermined") or {}).items():
        rows.append(f"  not determined  {name}: {why}")
    return "\n".join(rows)
