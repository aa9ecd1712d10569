"""``streamcal export CAL --format ardupilot|px4|c-header|json [-o FILE]``: a calibration in
the form its destination loads; what the destination cannot express is said on stderr and as
comments in the file."""
from __future__ import annotations

import sys

from ..export import FORMATS


def register(sub) -> None:
    p = sub.add_parser("export", help="write a calibration as autopilot parameters, a C header "
                       "or JSON",
                       description="Write a calibration in the form its destination loads: "
                                   "ArduPilot parameters, PX4 parameters, a C header for the "
                                   "Arduino sketch, or the calibration JSON (see docs/cli.md).")
    p.add_argument("calibration", metavar="CAL.json",
                   help="calibration file (docs/calibration_file.md)")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--firmware-version", metavar="VERSION",
                   help="--format ardupilot: the firmware the parameters are for, e.g. "
                        "'Copter 3.5' (before Copter 3.6, Plane 3.9, Rover 3.3, Sub 4.0 and "
                        "AntennaTracker 1.1 COMPASS_MOT is "
                        "added before the COMPASS_DIA/ODI matrix); default: the newest order")
    p.add_argument("-o", "--output", metavar="FILE", help="file to write (atomic); default (or -): stdout")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..atomic import atomic_write_text
    from ..calibration import Calibration
    from ..export import export

    cal = Calibration.load(args.calibration)
    text, notes = export(cal, args.format, args.firmware_version)
    for note in notes:
        print(f"streamcal export: {args.format} cannot express: {note}", file=sys.stderr)
    if args.output and args.output != "-":
        atomic_write_text(args.output, text, mode=0o644)
        print(f"written: {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
