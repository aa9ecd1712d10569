"""Options and reading shared by every command that reads a recording
(docs/tracks_and_inputs.md)."""
from __future__ import annotations

RECORDING_HELP = ("recording: track (.csv/.csv.gz), ArduPilot DataFlash .bin, PX4 .ulg, "
                  "MotionCal Raw: capture, or another CSV/TSV with --columns")


def add_input_options(parser, skip_bad_rows: bool = False) -> None:
    """Add ``--columns`` and ``--unit`` (and ``--skip-bad-rows`` when asked) to ``parser``."""
    parser.add_argument("--columns", metavar="MAP",
                        help="for another CSV/TSV: mx=NAME,my=NAME,mz=NAME[,t=NAME,ax=NAME,…,"
                             "temp=NAME,AUX=NAME]")
    parser.add_argument("--unit", choices=("uT", "nT", "mG", "G", "counts"),
                        help="magnetometer unit of a --columns file (default uT)")
    if skip_bad_rows:
        parser.add_argument("--skip-bad-rows", action="store_true",
                            help="skip and count malformed rows (or a cut last log message)")


def read_track(args, path=None):
    """The recording named by ``path`` (default ``args.track``) as a Track."""
    from ..inputs import read_recording

    return read_recording(args.track if path is None else path,
                          columns=getattr(args, "columns", None), unit=getattr(args, "unit", None),
                          skip_bad_rows=getattr(args, "skip_bad_rows", False))


def recording_chunks(args, rows: int):
    """The recording named by ``args.track`` as consecutive Tracks of at most ``rows`` rows when
    it is a section-1 track (read incrementally), else as one Track (autopilot logs, captures
    and mapped CSV files are read whole by their readers)."""
    from ..inputs.chunks import iter_track_chunks
    from ..inputs.detect import detect

    if getattr(args, "columns", None) is None and detect(args.track) == "track":
        return iter_track_chunks(args.track, rows=rows,
                                 skip_bad_rows=getattr(args, "skip_bad_rows", False))
    return iter([read_track(args)])
