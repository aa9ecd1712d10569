"""``streamcal check CAL RECORDING``: a calibration (a motor compensation, a refit) checked on a
flight it was not fitted on, against the calibration in force in that log (docs/cli.md)."""
from __future__ import annotations

import json

from ._common import RECORDING_HELP, add_input_options, read_track
from ._location import add_location_options, location_reference

#: How the words name each correction.
FORMULA = {"ardupilot": "ArduPilot's formula", "px4": "PX4's formula",
           "streamcal": "streamcal's own correction"}


def register(sub) -> None:
    p = sub.add_parser("check", help="check a calibration on another flight before loading it",
                       description="Apply a calibration (e.g. `fit FLIGHT --cal autopilot --add "
                                   "aux_interference=throttle -o new.json`) to another flight "
                                   "of the same vehicle with each autopilot's own correction "
                                   "formula and with streamcal's, and compare it with the "
                                   "calibration in force in that log: field-magnitude spread "
                                   "and heading error against the logged attitude (see "
                                   "docs/flight_logs.md).")
    p.add_argument("calibration", metavar="CAL",
                   help="calibration to check (JSON file, state dir, or 'autopilot'/'log': the "
                        "one in the recording's parameters)")
    p.add_argument("track", metavar="RECORDING", help=RECORDING_HELP)
    add_input_options(p, skip_bad_rows=True)
    p.add_argument("--split", choices=("first", "last"),
                   help="no second flight: refit CAL's motor term from the calibration in force "
                        "on the first (or last) half of RECORDING and check it on the other half")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    add_location_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..calibration import jsonable
    from ..errors import InputError
    from ..export.motor_check import flight_check, held_out_check
    from ..fitting.attitude_reference import calibration_in_force
    from ._calarg import calibration_for, follow_fitted_compass

    ref = location_reference(args)     # a mistyped --lat/--date said before the reading
    follow_fitted_compass(args, "calibration", "CAL")
    track = read_track(args)
    if track.mag is None or not len(track.t_mag):
        raise InputError(f"{args.track}: no magnetometer samples")
    if track.mag_unit != "uT":
        raise InputError(f"{args.track}: the readings are in {track.mag_unit}; the firmwares' "
                         "formulas take a field in physical units (give --unit)")
    cal, source = calibration_for(args.calibration, track, "CAL")
    if cal.sensor != "mag" or cal.unit != "uT":
        raise InputError(f"{args.calibration}: a magnetometer calibration in µT is needed, this "
                         f"one is for {cal.sensor!r} in {cal.unit!r}")
    _say_other_compass(args, cal, track)
    in_force = calibration_in_force(track)
    firmware = "px4" if track.metadata.get("input_format") == "px4-ulog" else "ardupilot"
    names = {"cal": args.calibration, "recording": args.track, "firmware": firmware}
    try:
        if args.split:
            out = held_out_check(track, in_force, _split_channel(args, cal, in_force),
                                 fit_on=args.split, ref=ref)
        else:
            out = flight_check(track, cal, in_force, ref=ref)
    except InputError as exc:
        raise InputError(f"{args.calibration} on {args.track}: {exc}") from None
    out = {**names, "in_force": _in_force_words(in_force), **out}
    if args.json:
        print(json.dumps(jsonable(out), allow_nan=False))
        return 0
    print("\n".join(_split_text(out) if args.split else _check_text(out)))
    return 0


def _say_other_compass(args, cal, track) -> None:
    """A line on stderr when CAL was fitted for another compass than the one read."""
    import sys

    fitted = (cal.extra or {}).get("compass_instance")
    read = track.metadata.get("compass_instance")
    if fitted is not None and read is not None and int(fitted) != int(read):
        print(f"streamcal check: {args.calibration} was fitted for compass {int(fitted)}, "
              f"{args.track} is read at compass {int(read)} (give --compass {int(fitted)})",
              file=sys.stderr)


def _split_channel(args, cal, in_force) -> str:
    """The motor channel ``--split`` refits: the one CAL's exported term takes."""
    from ..errors import InputError
    from ..export.common import motor_channel
    from ..export.motor_check import needed_channels

    if in_force is None:
        raise InputError(f"--split: {args.track} carries no autopilot compass calibration to "
                         "refit from (ArduPilot COMPASS_*, PX4 CAL_MAGn_*)")
    channel = motor_channel(needed_channels(cal))[0]
    if channel is None:
        raise InputError(f"--split: {args.calibration} has no motor term (aux_interference on "
                         "the throttle or a battery current) to refit")
    return channel


def _in_force_words(cal) -> str:
    if cal is None:
        return "the readings as logged (the log carries no compass calibration)"
    return f"the calibration in force ({(cal.extra or {}).get('source') or 'the log'})"


def _num(v: float) -> str:
    """A figure in words: one decimal, two under 1."""
    return f"{v:.1f}" if abs(v) >= 1 else f"{v:.2f}"


def _cell(v) -> str:
    return f"{v:>10.2f}" if v is not None else f"{'–':>10}"


HEADS = ("spread %", "robust %", "head. rms °", "head. p95 °")


def _table(rows: list[tuple[str, dict, str]]) -> list[str]:
    """Rows ``(label, figures, motor channel)`` under one header."""
    width = max(len(r[0]) for r in rows) + 2
    out = [f"  {'calibration':<{width}}" + "".join(f"{h:>12}" for h in HEADS) + "  motor term on"]
    for label, f, motor in rows:
        out.append(f"  {label:<{width}}" + "".join(
            f"{_cell(f.get(k)):>12}" for k in ("spread_pct", "spread_robust_pct",
                                                "heading_rms_deg", "heading_p95_deg"))
                   + f"  {motor}".rstrip())
    return out


def _samples(out: dict, n: int) -> str:
    def grouped(k: int) -> str:
        return f"{k:,}".replace(",", " ")

    text = f"{grouped(n)} samples"
    if out.get("n_heading"):
        text += f", {grouped(out['n_heading'])} with attitude"
    return text


def _changes(before: dict, after: dict, comp: dict) -> dict:
    """``{"lowers"|"raises"|"leaves": [phrases]}``: what each figure did."""
    out = {"lowers": [], "raises": [], "leaves": []}
    for key, unit, what, move in (("spread_pct", " %", "the field-magnitude spread",
                                   comp["spread"]),
                                  ("heading_rms_deg", "°", "the heading error", comp["heading"])):
        if move is None:
            continue
        rms = " rms" if key == "heading_rms_deg" else ""
        span = f"{_num(before[key])}{unit} to {_num(after[key])}{unit}{rms}"
        if move == "same":
            out["leaves"].append(f"{what} about the same ({span.replace(' to ', ' → ')})")
        else:
            out["lowers" if move == "lower" else "raises"].append(f"{what} from {span}")
    return out


def _said(verb: str, phrases: list[str]) -> str:
    return f"{verb} {' and '.join(phrases)}" if phrases else ""


def _verdict(subject: str, out: dict, before: dict, after: dict, comp: dict,
             keep: str) -> list[str]:
    """The plain sentences: what the calibration did on the checked samples, and the advice."""
    n = out["n"] if "n" in out else out["n_checked"]
    detail = f"({FORMULA[out['firmware']]}, {_samples(out, n)})"
    ch = _changes(before, after, comp)
    if comp["worse"]:
        lines = [f"{subject} {_said('raises', ch['raises'])} {detail}: it is worse than {keep}; "
                 f"keep {keep}."]
        rest = [p for p in (_said("lowers", ch["lowers"]), _said("leaves", ch["leaves"])) if p]
        if rest:
            lines.append(f"It {' and '.join(rest)}.")
    else:
        said = " and ".join(p for p in (_said("lowers", ch["lowers"]),
                                        _said("leaves", ch["leaves"])) if p)
        lines = [f"{subject} {said} {detail}"
                 + ("." if comp["better"] else f": no clear gain over {keep}.")]
    if "heading" in out:
        lines.append(f"{out['heading'][0].upper()}{out['heading'][1:]}.")
    return lines


def _check_text(out: dict) -> list[str]:
    from pathlib import Path

    fw, name = out["firmware"], Path(out["cal"]).name
    logged = "logged" in out["before"]
    before = out["before"]["logged" if logged else fw]
    keep = "the readings as logged" if logged else "the calibration in force"
    lines = _verdict(f"On this flight {name}", out, before, out["after"][fw],
                     out["compare"][fw], keep)
    rows = ([("as logged", before, "")] if logged else
            [(f"in force ({FORMULA[k]})", out["before"][k], "") for k in ("ardupilot", "px4")])
    rows += [(f"{name} ({FORMULA[k]})", out["after"][k], out["channels"][k] or "none")
             for k in ("ardupilot", "px4")]
    rows.append((f"{name} ({FORMULA['streamcal']})", out["after"]["streamcal"],
                 "every channel"))
    return lines + ["", f"before: {out['in_force']}"] + _table(rows) + [
        f"n = {_samples(out, out['n'])}", f"rule: {out['compare'][fw]['rule']}"]


def _split_text(out: dict) -> list[str]:
    fw = out["firmware"]
    a, b = out["checked_s"]
    subject = (f"Fitted on the {out['fit_on']} half of this flight and checked on the other "
               f"({a:.0f}–{b:.0f} s), a motor term on {out['channel']}")
    comp = out["compare"][fw]
    lines = _verdict(subject, out, out["before"][fw], out["after"][fw], comp,
                     "the calibration in force")
    rows = [("in force", out["before"][fw], ""),
            ("refit without a motor term", out["refit"][fw], "")]
    rows += [(f"+ motor term ({FORMULA[k]})", out["after"][k], out["channel"])
             for k in ("ardupilot", "px4")]
    rows.append((f"+ motor term ({FORMULA['streamcal']})", out["streamcal"], out["channel"]))
    g = ", ".join(f"{v:.3g}" for v in out["g_uT"])
    return lines + ["", f"before: {out['in_force']}"] + _table(rows) + [
        f"motor term fitted: ({g}) µT per unit of {out['channel']}",
        f"n = {_samples(out, out['n_checked'])}", f"rule: {comp['rule']}"]
