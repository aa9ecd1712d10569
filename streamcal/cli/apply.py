"""``streamcal apply CAL.json LOG -o OUT.csv``: calibrated field (µT), unit direction and, with
an accelerometer, tilt-compensated magnetic heading per magnetometer sample."""
from __future__ import annotations

import sys

import numpy as np

from ._common import RECORDING_HELP, add_input_options, read_track


def register(sub) -> None:
    p = sub.add_parser("apply", help="apply a calibration to a recording",
                       description="Write the calibrated field (µT), the unit direction and, "
                                   "with an accelerometer, the tilt-compensated heading of every "
                                   "magnetometer sample of a recording to a CSV file (see "
                                   "docs/cli.md).")
    p.add_argument("calibration", metavar="CAL.json",
                   help="calibration file (docs/calibration_file.md)")
    p.add_argument("track", metavar="LOG", help=RECORDING_HELP)
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv", help="file to write (atomic)")
    add_input_options(p, skip_bad_rows=True)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..calibration import Calibration
    from ..errors import InputError
    from ..export.apply import apply_calibration, write_applied

    cal = Calibration.load(args.calibration)
    track = read_track(args)
    if not track.mag_rows.any():
        raise InputError(f"{args.track}: no magnetometer rows (mx,my,mz)")
    if track.mag_unit != cal.unit:
        raise InputError(f"{args.track}: magnetometer in {track.mag_unit}, the calibration in "
                         f"{cal.unit}")
    cov = track.covariates_at_mag()
    accel = np.column_stack([cov[c] for c in ("ax", "ay", "az")]) \
        if all(c in cov for c in ("ax", "ay", "az")) else None
    applied = apply_calibration(cal, track.t_mag, track.mag, cov, accel)
    meta = {"streamcal-applied": "1", "calibration": str(args.calibration),
            "recording": str(args.track),
            "field": (f"|B| = {applied.field_scale:.6g} {cal.unit} (the calibration's field)"
                      if applied.field_known else
                      f"|B| unknown: fields scaled by K's mean radius {applied.field_scale:.6g} "
                      f"{cal.unit}"),
            "heading": ("degrees from magnetic north of body x, tilt-compensated with the "
                        "accelerometer" if accel is not None else "none: no accelerometer")}
    write_applied(args.output, applied, meta)
    norm = np.linalg.norm(applied.field, axis=1)
    from ..units import display_unit

    print(f"{args.output}: {len(norm)} samples, |field| {np.mean(norm):.4g} ± {np.std(norm):.2g} "
          f"{display_unit(cal.unit)}")
    if not applied.field_known:
        print("streamcal apply: the calibration has no field strength; |field| is in units of "
              "K's mean radius", file=sys.stderr)
    return 0
