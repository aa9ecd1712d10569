"""``streamcal apply CAL.json LOG -o OUT.csv``: calibrated field (µT), unit direction and, with
an accelerometer, tilt-compensated magnetic heading per magnetometer sample."""
from __future__ import annotations

import sys

import numpy as np

from ._common import RECORDING_HELP, add_input_options, read_track, recording_chunks
from ._output import messages_to


def register(sub) -> None:
    p = sub.add_parser("apply", help="apply a calibration to a recording",
                       description="Write the calibrated field (µT), the unit direction and, "
                                   "with an accelerometer, the tilt-compensated heading of every "
                                   "magnetometer sample of a recording to a CSV file (see "
                                   "docs/cli.md).")
    p.add_argument("calibration", metavar="CAL.json",
                   help="calibration file (docs/calibration_file.md)")
    p.add_argument("track", metavar="LOG", help=RECORDING_HELP)
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv",
                   help="file to write (atomic; - for stdout)")
    add_input_options(p, skip_bad_rows=True)
    p.set_defaults(func=run)


#: Rows per chunk of a section-1 track (memory is bounded by a chunk, not by the recording;
#: 20 000 rows keep the parser's temporaries near 20 MiB: bench_replay_memory).
CHUNK_ROWS = 20_000


def run(args) -> int:
    from ..calibration import Calibration
    from ..errors import InputError
    from ..export.apply_stream import applied_chunks, write_applied_chunks
    from ..inputs.track import Track

    cal = Calibration.load(args.calibration)
    from ._calarg import follow_fitted_compass

    follow_fitted_compass(args, "calibration", "CAL.json")
    if getattr(args, "unit", None) is not None:
        chunks = iter([read_track(args)])        # read_track explains --unit on a track
    else:
        chunks = recording_chunks(args, rows=CHUNK_ROWS)
    stats = np.zeros(3)                           # samples, sum |f|, sum |f|^2
    field = {}

    def checked():
        for k, chunk in enumerate(chunks):
            if k == 0 and chunk.mag_unit != cal.unit:
                raise InputError(f"{args.track}: magnetometer in {chunk.mag_unit}, the "
                                 f"calibration in {cal.unit}")
            yield chunk

    def pieces():
        for piece in applied_chunks(cal, checked(), Track):
            norm = np.linalg.norm(piece.field, axis=1)
            stats[:] += (len(norm), norm.sum(), np.square(norm).sum())
            field.update(scale=piece.field_scale, known=piece.field_known)
            yield piece
        if not stats[0]:
            raise InputError(f"{args.track}: no magnetometer rows (mx,my,mz)")

    def meta(piece):
        return {"streamcal-applied": "1", "calibration": str(args.calibration),
                "recording": str(args.track),
                "field": (f"|B| = {piece.field_scale:.6g} {cal.unit} (the calibration's field)"
                          if piece.field_known else
                          f"|B| unknown: fields scaled by K's mean radius "
                          f"{piece.field_scale:.6g} {cal.unit}"),
                "heading": ("degrees from magnetic north of body x, tilt-compensated with the "
                            "accelerometer" if piece.heading_deg is not None
                            else "none: no accelerometer")}

    write_applied_chunks(args.output, pieces(), meta)
    n, total, squares = stats
    mean = total / n
    from ..units import display_unit

    print(f"{args.output}: {int(n)} samples, |field| {mean:.4g} ± "
          f"{np.sqrt(max(squares / n - mean * mean, 0.0)):.2g} {display_unit(cal.unit)}",
          file=messages_to(args.output))
    if not field["known"]:
        print("streamcal apply: the calibration has no field strength; |field| is in units of "
              "K's mean radius", file=sys.stderr)
    return 0
