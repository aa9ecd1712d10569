"""``diagnose``/``report`` with ``--compass all``: each compass of an autopilot log diagnosed,
then the compasses compared (SPEC §6; :mod:`streamcal.diagnosis.compass_consistency`)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..calibration import jsonable
from ..errors import InsufficientDataError
from ._common import _command, recording_argv, say_read_warnings, verdict_line


def _diagnose_each(args, model) -> list[dict]:
    """Per compass: ``{"instance", "device_id", "track", "diagnosis" (object or None),
    "error", "autopilot_cal" (or None)}``; a compass the data cannot calibrate keeps its error.
    ``--lat/--lon`` (else the log's GPS) is the place of every compass's heading error."""
    from ..diagnosis import diagnose
    from ..errors import InputError
    from ..inputs import autopilot_calibration, read_compasses
    from ._location import beside_diagnosis, location_reference

    ref = location_reference(args)
    tracks = read_compasses(args.track)
    say_read_warnings(args.track, tracks[0], _command(args))
    out = []
    for track in tracks:
        md = track.metadata
        entry = {"instance": int(md.get("compass_instance", 0)),
                 "device_id": int(md["compass_device_id"]) if md.get("compass_device_id")
                 else None, "track": track, "diagnosis": None, "error": None}
        try:
            entry["autopilot_cal"] = autopilot_calibration(track)
        except InputError:
            entry["autopilot_cal"] = None
        kwargs = {"location": ref, "cal_arg": getattr(args, "cal", None),
                  "recording": recording_argv(argparse.Namespace(
                      **{**vars(args), "compass": str(entry["instance"])}))}
        if getattr(args, "cal", None):
            from ._calarg import calibration_for

            cal, source = calibration_for(args.cal, track)
            kwargs.update(calibration=cal, calibration_source=source)
        try:
            entry["diagnosis"] = diagnose(track, model=model, **kwargs)
        except InsufficientDataError as exc:
            entry["error"] = str(exc)
        else:
            entry.update(beside_diagnosis(track, entry["diagnosis"]))
        out.append(entry)
    return out


def _consistency(entries: list[dict], limits) -> list:
    """Pairs under the autopilot's calibration (where every compass has one) and under
    streamcal's (the diagnosed compasses), judged by ``limits``."""
    from ..diagnosis.compass_consistency import compare_all, compass_field

    pairs = []
    for label, get in (("autopilot", lambda e: e["autopilot_cal"]),
                       ("streamcal", lambda e: getattr(e["diagnosis"], "calibration", None))):
        fields = [compass_field(e["track"], get(e), e["instance"],
                                float(e["track"].metadata.get("log_t0_s", 0.0)))
                  for e in entries if get(e) is not None]
        pairs += compare_all(fields, label, limits)
    _mark_ardupilot_checks(entries, pairs)
    return pairs


def consistency_limits(entries: list[dict]):
    """The consistency limits of the log's firmware (:func:`~streamcal.diagnosis.
    compass_consistency.limits_for`, from the first compass's metadata)."""
    from ..diagnosis.compass_consistency import CURRENT, limits_for

    if not entries:
        return CURRENT
    md = entries[0]["track"].metadata
    return limits_for(md.get("firmware"), md.get("input_format"))


def _mark_ardupilot_checks(entries: list[dict], pairs: list) -> None:
    """On an ArduPilot log, set each pair's ``ardupilot_checks``: ArduPilot's consistency test
    (``Compass::consistent``) compares each compass used for yaw (COMPASS_USEn not 0) with the
    primary only."""
    from ..inputs.autopilot_cal import ardupilot_param

    if not entries or entries[0]["track"].metadata.get("input_format") != "ardupilot-dataflash":
        return
    primary = int(entries[0]["track"].metadata.get("compass_default", entries[0]["instance"]))
    used = {}
    for e in entries:
        md = e["track"].metadata
        name = ardupilot_param("USE", int(md.get("compass_params_index", e["instance"])))
        used[e["instance"]] = float(md.get(f"param.{name}", 1.0)) != 0
    for p in pairs:
        p.ardupilot_checks = primary in (p.a, p.b) and used.get(p.a, True) and used.get(p.b, True)


def _entry_json(e: dict) -> dict:
    out = {"instance": e["instance"], "device_id": e["device_id"],
           "diagnosis": e["diagnosis"].to_dict() if e["diagnosis"] is not None else None}
    out.update({k: e[k] for k in PLACE_KEYS if k in e})
    if e["error"]:
        out["error"] = e["error"]
    return out


#: The keys :func:`._location.beside_diagnosis` adds to a compass's entry, as in single-compass ``diagnose --json``.
PLACE_KEYS = ("reference_field", "attitude_reference", "orientation")


def _place_lines(e: dict) -> list[str]:
    from ..geomag import text_lines
    from ._location import attitude_lines

    if "reference_field" not in e:
        return []
    return [""] + text_lines(e["reference_field"]) + attitude_lines(e)


def _terminal_lines(e: dict) -> list[str]:
    """What ``report --compass all`` says of one compass on the terminal, as ``diagnose
    --compass all`` begins it: the compass, its verdict, the local field and the attitude
    reference (or why there is no calibration)."""
    if e["diagnosis"] is None:
        return [_compass_title(e), f"no calibration: {e['error']}"]
    return [_compass_title(e), verdict_line(e["diagnosis"])] + _place_lines(e)[1:]


def _pair_line(p: dict) -> str:
    def f(v, fmt=".3g"):
        return "–" if v is None else format(v, fmt)

    return (f"  {p['a']}–{p['b']}  {p['calibration']:<9} {f(p['angle_deg_median']):>8} "
            f"{f(p['angle_deg_p95']):>8} {f(p['xy_angle_deg_median']):>10} "
            f"{f(p['xy_angle_deg_p95']):>10} {f(p['fraction_inconsistent']):>12}   {p['n']}")


def _table(pairs: list[dict], limits) -> str:
    table = ["consistency (angles in degrees between calibrated field vectors; horizontal: "
             + (pairs[0]["xy_plane"] if pairs else "-") + ")",
             "  pair calibration  median      p95  horiz med  horiz p95  inconsistent   n"]
    table += [_pair_line(p) for p in pairs] or ["  (fewer than two compasses: nothing to compare)"]
    table.append(f"limits: {limits.text}")
    if any(p.get("ardupilot_checks") is not None for p in pairs):
        checked = list(dict.fromkeys(f"{p['a']}–{p['b']}" for p in pairs
                                     if p.get("ardupilot_checks")))
        table.append("ArduPilot's own test compares the primary with each compass used for yaw "
                     f"only: {', '.join(checked) or 'none of these pairs'}")
    return "\n".join(table)


def _compass_title(e: dict) -> str:
    """``compass 1 (device id 97795)``."""
    return f"compass {e['instance']}" + (f" (device id {e['device_id']})"
                                         if e["device_id"] else "")


def _text(entries: list[dict], pairs: list[dict], describe, limits) -> str:
    """One paragraph per compass (``describe(diagnosis)``), then the consistency table."""
    parts = []
    for e in entries:
        head = _compass_title(e)
        body = ("\n".join([describe(e["diagnosis"])] + _place_lines(e))
                if e["diagnosis"] is not None else f"no calibration: {e['error']}")
        parts.append(f"{head}\n{body}")
    return "\n\n".join(parts + [_table(pairs, limits)])


def _plots(directory, entries: list[dict], pairs) -> str:
    """Each compass's figures into ``DIRECTORY/compass_N/``, the consistency figure into
    ``DIRECTORY``; the line saying how many PNG files were written where."""
    from pathlib import Path

    from ..atomic import atomic_write_bytes
    from ..report import write_diagnosis_plots
    from ..report.figures_compasses import consistency_figure

    written = []
    for e in entries:
        written += write_diagnosis_plots(e["diagnosis"], e["track"],
                                         Path(directory) / f"compass_{e['instance']}",
                                         reason=e["error"])
    if pairs:
        fig = consistency_figure(pairs)
        path = Path(directory) / f"{fig.name}.png"
        atomic_write_bytes(path, fig.png, mode=0o644)
        written.append(path)
    return f"plots: {len(written)} PNG files written to {Path(directory).resolve()}"


def diagnose_all(args, model, describe=str) -> int:
    """Print the per-compass diagnoses (``describe(diagnosis)`` each) and the consistency table
    (or one JSON object); exit 1 when no compass could be calibrated."""
    entries = _diagnose_each(args, model)
    limits = consistency_limits(entries)
    pairs = _consistency(entries, limits)
    dicts = [p.to_dict() for p in pairs]
    plots = _plots(args.plots, entries, pairs) if getattr(args, "plots", None) else ""
    if args.json:
        print(json.dumps(jsonable({"compasses": [_entry_json(e) for e in entries],
                                   "consistency": dicts,
                                   "consistency_limits": limits.to_dict()}),
                         allow_nan=False))
    else:
        print(_text(entries, dicts, describe, limits))
    if plots:
        print(plots, file=sys.stderr if args.json else sys.stdout)
    return 0 if any(e["diagnosis"] is not None for e in entries) else 1


def report_all(args, model, output) -> int:
    """Write one page (``output``: a path or ``-``): the compasses compared, a section per
    compass (verdict, plain sentences, heading error, ladder), then the full report of the
    compass the autopilot uses first."""
    from ..report import write_report
    from ..report.figure_data import unit_label
    from ..report.figures_compasses import compasses_section, consistency_figure
    from ..report.html import diagnosis_section
    from ._output import check_output, messages_to

    check_output(output)
    entries = _diagnose_each(args, model)
    limits = consistency_limits(entries)
    pairs = _consistency(entries, limits)
    default = entries[0]["track"].metadata.get("compass_default", str(entries[0]["instance"]))
    first = next((e for e in entries if str(e["instance"]) == default), entries[0])
    figure = consistency_figure(pairs) if pairs else None
    sections = [compasses_section([_entry_json(e) for e in entries], pairs, figure, limits)]
    sections += [diagnosis_section(e["diagnosis"], unit_label(e["track"].mag_unit),
                                   title=_compass_title(e), anchor=f"compass-{e['instance']}",
                                   reason=e["error"]) for e in entries]
    sections.append(f'<h2 id="default-compass">{_compass_title(first)}, the one the autopilot '
                    "uses first: every figure and table</h2>")
    out = write_report(output, first["track"], first["diagnosis"], reason=first["error"],
                       intro="\n".join(sections), name=Path(args.track).name)
    say = messages_to(out)
    for e in entries:
        print("\n".join(_terminal_lines(e)) + "\n", file=say)
    print(_table([p.to_dict() for p in pairs], limits), file=say)
    print(f"report written to {out}", file=say)
    if all(e["diagnosis"] is None for e in entries):
        print(f"streamcal report: no calibration of any compass ({first['error']})",
              file=sys.stderr)
        return 1
    return 0
