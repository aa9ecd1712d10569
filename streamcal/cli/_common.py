"""Options and reading shared by every command that reads a recording
(docs/tracks_and_inputs.md)."""
from __future__ import annotations

import sys

RECORDING_HELP = ("recording: track (.csv/.csv.gz), ArduPilot DataFlash .bin, PX4 .ulg, ROS 1 "
                  ".bag, ROS 2 bag directory, MotionCal Raw: capture, or another CSV/TSV with "
                  "--columns")


def compass_choice(text: str):
    """``--compass`` value: an instance number from 0, or ``"all"``."""
    import argparse

    if text == "all":
        return text
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an instance number from 0 or 'all', got "
                                         f"{text!r}")
    return value


def add_compass_option(parser) -> None:
    """Add ``--compass N|all`` (which compass of an autopilot log)."""
    parser.add_argument("--compass", type=compass_choice, default=None, metavar="N|all",
                        help="autopilot log: compass instance from 0 (ArduPilot MAG=0, MAG2=1, "
                             "MAG3=2; PX4 the sensor_mag instance); 'all' (diagnose, report) "
                             "diagnoses and compares every compass; default: the compass the "
                             "autopilot uses first")


def add_input_options(parser, skip_bad_rows: bool = False) -> None:
    """Add ``--columns``, ``--unit``, ``--topic`` and ``--compass`` (and ``--skip-bad-rows`` when asked) to
    ``parser``."""
    parser.add_argument("--columns", metavar="MAP",
                        help="for another CSV/TSV: mx=NAME,my=NAME,mz=NAME[,t=NAME,ax=NAME,…,"
                             "temp=NAME,AUX=NAME]")
    parser.add_argument("--unit", choices=("uT", "nT", "mG", "G", "counts"),
                        help="magnetometer unit of a --columns file (default uT)")
    parser.add_argument("--topic", action="append", metavar="NAME",
                        help="for a ROS bag with several topics of a message type: the one to "
                             "read (repeatable, one per type)")
    add_compass_option(parser)
    if skip_bad_rows:
        add_skip_bad_rows(parser)


def add_skip_bad_rows(parser) -> None:
    """Add ``--skip-bad-rows`` alone (for commands without ``--columns``/``--unit``)."""
    parser.add_argument("--skip-bad-rows", action="store_true",
                        help="skip and count malformed rows of a text recording; the count and "
                             "the first one are printed on stderr (an autopilot log is always read "
                             "to its last complete message, what was lost said on stderr)")


def skipped_text(path, skipped: int, reasons) -> str:
    """``skipped 3 bad rows of PATH (first: line 12 column 'mx': …)``; "" when none."""
    if not skipped:
        return ""
    first = f" (first: {reasons[0]})" if reasons else ""
    return f"skipped {skipped} bad row{'s' if skipped != 1 else ''} of {path}{first}"


def say_skipped(path, skipped: int, reasons, command: str = "streamcal") -> None:
    """Print :func:`skipped_text` on stderr when rows were skipped."""
    text = skipped_text(path, skipped, reasons)
    if text:
        print(f"{command}: {text}", file=sys.stderr)


def say_read_warnings(path, track, command: str = "streamcal") -> None:
    """One line on stderr when an autopilot log was cut or damaged: what was lost."""
    text = track.metadata.get("read_warnings")
    if text:
        print(f"{command}: {path}: read what was intact; lost: {text}", file=sys.stderr)


def read_track(args, path=None):
    """The recording named by ``path`` (default ``args.track``) as a Track; rows skipped by
    ``--skip-bad-rows`` are counted on stderr, so is what a cut or damaged log lost."""
    from ..errors import InputError
    from ..inputs import read_recording

    path = args.track if path is None else path
    compass = getattr(args, "compass", None)
    if compass == "all":
        raise InputError(f"--compass all: {_command(args)} reads one compass; give its instance "
                         "number (diagnose and report compare every compass)")
    track = read_recording(path, columns=getattr(args, "columns", None),
                           unit=getattr(args, "unit", None),
                           skip_bad_rows=getattr(args, "skip_bad_rows", False),
                           topics=getattr(args, "topic", None), compass=compass)
    say_skipped(path, getattr(track, "skipped_rows", 0), getattr(track, "skip_reasons", ()),
                _command(args))
    say_read_warnings(path, track, _command(args))
    return track


def fake_track_reader(args):
    """``(path) -> Track`` for a ``fake:TRACK.csv`` device: honours ``--skip-bad-rows`` and
    counts the skipped rows on stderr."""
    def read(path):
        from ..inputs.track import Track

        skip = getattr(args, "skip_bad_rows", False)
        track = Track.read(path, skip_bad_rows=skip)
        say_skipped(path, track.skipped_rows, track.skip_reasons, _command(args))
        return track

    return read


def _command(args) -> str:
    name = getattr(args, "command", None) or getattr(getattr(args, "func", None), "__module__",
                                                       "").rpartition(".")[2]
    return f"streamcal {name}" if name else "streamcal"


def recording_chunks(args, rows: int):
    """The recording named by ``args.track`` as consecutive Tracks: a section-1 track of at
    most ``rows`` rows each and an ArduPilot DataFlash log piece by piece (both read
    incrementally, memory bounded by the piece), a PX4 ULog read whole and given out in slices
    of ``rows`` rows, else one Track (captures and mapped CSV files are read whole by their
    readers)."""
    from ..inputs.chunks import iter_track_chunks
    from ..inputs.detect import detect

    compass = getattr(args, "compass", None)
    kind = detect(args.track) if compass != "all" else None   # the file's head read once
    if getattr(args, "columns", None) is None and compass is None and kind == "track":
        return _counted(args, iter_track_chunks(args.track, rows=rows,
                                                skip_bad_rows=getattr(args, "skip_bad_rows",
                                                                      False)))
    if getattr(args, "columns", None) is None and getattr(args, "unit", None) is None \
            and not getattr(args, "topic", None) and kind == "dataflash":
        return _warned(args, _dataflash_chunks(args.track, compass))
    if kind == "ulog":
        # read whole, given out in slices (views): no whole copy downstream
        return _whole_in_slices(args, rows)
    return iter([read_track(args)])


def _whole_in_slices(args, rows: int):
    track = read_track(args)
    for a in range(0, max(len(track), 1), rows):
        yield track.select(slice(a, a + rows))


def _dataflash_chunks(path, compass):
    from pathlib import Path

    from ..inputs.dataflash_chunks import iter_dataflash_chunks

    yield from iter_dataflash_chunks(Path(path), compass=compass)


def _warned(args, chunks):
    """The chunks unchanged; what a cut or damaged log lost is said on stderr with the first."""
    for k, chunk in enumerate(chunks):
        if not k:
            say_read_warnings(args.track, chunk, _command(args))
        yield chunk


def _counted(args, chunks):
    """The chunks unchanged; once they are exhausted, the rows skipped over all of them are
    counted on stderr (first reason of the first chunk that skipped any)."""
    skipped, reasons = 0, []
    for chunk in chunks:
        skipped += chunk.skipped_rows
        reasons = reasons or list(chunk.skip_reasons)
        yield chunk
    say_skipped(args.track, skipped, reasons, _command(args))


#: The input options a recording was read with, as ``(dest, flag)``: repeated in a command a
#: diagnosis recommends, so that it reads the recording the same way.
INPUT_FLAGS = (("columns", "--columns"), ("unit", "--unit"), ("topic", "--topic"),
               ("compass", "--compass"), ("skip_bad_rows", "--skip-bad-rows"))


def recording_argv(args) -> list[str]:
    """The recording and the input options it was read with, as command-line words."""
    words = [str(args.track)]
    for dest, flag in INPUT_FLAGS:
        value = getattr(args, dest, None)
        if value is True:
            words.append(flag)
        elif value not in (None, False):
            words += [flag, str(value)]
    return words


def verdict_line(d) -> str:
    """``verdict    effect_missing   (rule: …)``: the verdict and the rule that gave it."""
    rule = d.significance_rule if d.verdict == "effect_missing" else d.noise_floor_rule
    return f"verdict    {d.verdict}   (rule: {rule})"
