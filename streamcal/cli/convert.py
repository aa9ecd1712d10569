"""``streamcal convert LOG -o TRACK.csv``: any supported recording → a track
(docs/tracks_and_inputs.md)."""
from __future__ import annotations

from ._common import RECORDING_HELP, add_input_options, read_track, recording_chunks
from ._output import messages_to

#: Rows per chunk of a section-1 track (memory is bounded by a chunk, not by the recording;
#: 20 000 rows keep the parser's temporaries near 20 MiB: bench_replay_memory).
CHUNK_ROWS = 20_000


def register(sub) -> None:
    p = sub.add_parser("convert", help="convert a recording (autopilot log, Raw: capture, CSV) "
                       "to a track",
                       description="Convert any supported recording to a track file (units, axes "
                                   "and provenance in its metadata; see "
                                   "docs/tracks_and_inputs.md).")
    p.add_argument("track", metavar="LOG", help=RECORDING_HELP)
    p.add_argument("-o", "--output", required=True, metavar="TRACK.csv",
                   help="track to write (atomic; .csv.gz compresses; - for stdout)")
    add_input_options(p, skip_bad_rows=True)
    p.set_defaults(func=run)


def run(args) -> int:
    if getattr(args, "unit", None) is not None:   # read_track explains --unit on a track
        track = read_track(args)
        track.write(args.output)
        _say(args, len(track), len(track.t_mag), track.t[-1] - track.t[0], track)
        return 0
    from ..inputs.track_writer import track_writer

    rows = mag = 0
    first = last = None
    with track_writer(args.output) as write:
        for chunk in recording_chunks(args, rows=CHUNK_ROWS):
            write(chunk)
            rows, mag = rows + len(chunk), mag + len(chunk.t_mag)
            if len(chunk):
                first = chunk.t[0] if first is None else first
                last, kept = chunk.t[-1], chunk
    _say(args, rows, mag, last - first, kept)
    return 0


def _say(args, rows: int, mag: int, seconds: float, track) -> None:
    say = messages_to(args.output)
    print(f"{args.output}: {rows} rows, {mag} mag samples, {seconds:.1f} s, columns "
          f"{','.join(track.columns)}", file=say)
    for key in ("mag_offsets_undone", "mag_calibration_undone", "read_warnings"):
        if key in track.metadata:
            print(f"  {key}: {track.metadata[key]}", file=say)
