"""``streamcal report TRACK [--model a,b] [--add EFFECT] -o report.html`` (docs/cli.md).

Diagnoses the track and writes one self-contained HTML page of figures and tables. When the fit
refuses the track (too little coverage…), the page shows what needs no calibration and says why;
the exit code is then 1, as for ``streamcal fit``.
"""
from __future__ import annotations

import sys
from pathlib import Path

from ..calibration import DEFAULT_MODEL
from ._common import recording_argv, RECORDING_HELP, add_input_options, read_track
from ._location import add_location_options, location_reference
from ._output import check_output, messages_to


def register(subparsers) -> None:
    p = subparsers.add_parser("report", help="diagnose a track and write a self-contained HTML "
                              "report of figures",
                              description="Diagnose a recording and write the residuals, the "
                                          "candidate effects and the model ladder as figures "
                                          "into one self-contained HTML page (see "
                                          "docs/diagnosis.md).")
    p.add_argument("track", help=RECORDING_HELP)
    add_input_options(p, skip_bad_rows=True)
    p.add_argument("--model", default=",".join(DEFAULT_MODEL),
                   help="comma-separated effects (docs/effects.md; default: %(default)s)")
    p.add_argument("--add", action="append", default=[], metavar="EFFECT",
                   help="add an effect to the model (repeatable, or comma-separated)")
    p.add_argument("-o", "--output", metavar="HTML",
                   help="report file (default: <track name>-report.html in the current directory; "
                        "- for stdout)")
    p.add_argument("--cal", metavar="CAL", help="diagnose against this calibration (JSON file or "
                   "state dir; 'autopilot' or 'log': the one in the log's own parameters, "
                   "ArduPilot COMPASS_* or PX4 CAL_MAGn_*), holding what the track does not determine")
    add_location_options(p)
    p.set_defaults(func=run)


def model_from_args(model: str, add) -> tuple[str, ...]:
    """The model named by ``--model`` plus every ``--add`` (duplicates dropped, order kept)."""
    names = [n.strip() for n in model.split(",") if n.strip()]
    for item in add or ():
        names += [n.strip() for n in item.split(",") if n.strip()]
    return tuple(dict.fromkeys(names))


def default_output(track_path: str) -> Path:
    name = Path(track_path).name
    for suffix in (".gz", ".csv"):
        name = name[: -len(suffix)] if name.endswith(suffix) else name
    return Path(f"{name or 'track'}-report.html")


def run(args) -> int:
    from ..report import diagnose_or_reason, write_report

    from ..diagnosis.reference_field import reference_field
    from ..geomag import text_lines

    model = model_from_args(args.model, args.add)
    from ._calarg import follow_fitted_compass

    follow_fitted_compass(args)
    if getattr(args, "compass", None) == "all":
        from ._compasses import report_all
        return report_all(args, model, args.output or default_output(args.track))
    ref = location_reference(args)
    out = args.output or default_output(args.track)
    check_output(out)
    track = read_track(args)
    kwargs = {}
    if getattr(args, "cal", None):
        from ._calarg import calibration_for

        cal, source = calibration_for(args.cal, track)
        kwargs = {"calibration": cal, "calibration_source": source, "cal_arg": args.cal}
    diagnosis, reason = diagnose_or_reason(track, model, recording=recording_argv(args),
                                           location=ref, **kwargs)
    place = diagnosis.location if diagnosis is not None else ref   # the one the library used
    local = reference_field(track, getattr(diagnosis, "calibration", None), place,
                            gravity=getattr(diagnosis, "gravity", None))   # as diagnose does
    out = write_report(out, track, diagnosis, reason=reason, name=Path(args.track).name,
                       intro=_reference_html(text_lines(local)))
    say = messages_to(out)
    if local.get("source") is not None:    # without a reference, the page says why
        print("\n".join(text_lines(local)), file=say)
    print(f"report written to {out}", file=say)
    if diagnosis is None:
        print(f"streamcal report: no calibration: {reason} (the report shows the raw data)",
              file=sys.stderr)
        return 1
    return 0


def _reference_html(lines: list[str]) -> str:
    """The local-field comparison as a small HTML section for the report's intro."""
    from html import escape

    items = "".join(f"<li>{escape(line.strip())}</li>" for line in lines[1:])
    head = escape(lines[0].split("  ", 1)[-1].strip())
    return (f'<section id="reference-field"><h2>Local field</h2><p>{head}</p>'
            + (f"<ul>{items}</ul>" if items else "") + "</section>")
