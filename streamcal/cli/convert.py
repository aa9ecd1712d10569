"""``streamcal convert LOG -o TRACK.csv``: any supported recording → a track
(docs/tracks_and_inputs.md)."""
from __future__ import annotations

from ._common import RECORDING_HELP, add_input_options, read_track


def register(sub) -> None:
    p = sub.add_parser("convert", help="convert a recording (autopilot log, Raw: capture, CSV) "
                       "to a track",
                       description="Convert any supported recording to a track file (units, axes "
                                   "and provenance in its metadata; see "
                                   "docs/tracks_and_inputs.md).")
    p.add_argument("track", metavar="LOG", help=RECORDING_HELP)
    p.add_argument("-o", "--output", required=True, metavar="TRACK.csv",
                   help="track to write (atomic; .csv.gz compresses)")
    add_input_options(p, skip_bad_rows=True)
    p.set_defaults(func=run)


def run(args) -> int:
    track = read_track(args)
    track.write(args.output)
    print(f"{args.output}: {len(track)} rows, {len(track.t_mag)} mag samples, "
          f"{track.t[-1] - track.t[0]:.1f} s, columns {','.join(track.columns)}")
    for key in ("mag_offsets_undone", "mag_calibration_undone", "read_warnings"):
        if key in track.metadata:
            print(f"  {key}: {track.metadata[key]}")
    return 0
