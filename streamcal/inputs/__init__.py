"""Reading recordings: one entry point for every command that reads one.

    track = read_recording("flight.BIN")                      # ArduPilot DataFlash
    track = read_recording("log.ulg")                         # PX4 ULog
    track = read_recording("capture.txt")                     # MotionCal Raw: lines
    track = read_recording("run.bag", topics=["/imu/mag"])    # ROS 1 bag (a ROS 2 bag: its dir)
    track = read_recording("other.tsv", columns="mx=Bx,my=By,mz=Bz,t=time", unit="nT")

The format is detected from the content (:mod:`.detect`). Every reader returns a
:class:`~streamcal.inputs.track.Track` in docs/tracks_and_inputs.md units, with units, axes and
provenance in its
metadata, and raises :class:`~streamcal.errors.InputError` (or its subclass ``TrackError``)
naming the file and what is wrong or missing.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Mapping

from ..errors import InputError, TrackError
from .track import Track
from .autopilot_cal import (MOTOR_AFTER_MATRIX, calibration_from_ardupilot,
                            calibration_from_px4, px4_rotation)
from .columns import parse_columns, parse_unit
from .detect import FORMATS, detect

if TYPE_CHECKING:   # for the return annotation of autopilot_calibration only
    from ..calibration import Calibration

__all__ = ["read_recording", "read_compasses", "detect", "FORMATS", "autopilot_calibration",
           "calibration_from_ardupilot", "calibration_from_px4"]


def read_recording(path, *, columns: str | Mapping[str, str] | None = None,
                   unit: str | None = None, skip_bad_rows: bool = False,
                   topics=None, compass: int | None = None) -> Track:
    """Read any supported recording into a Track.

    Args:
        path: the file (``.csv``/``.csv.gz`` track, ``.bin``, ``.ulg``, ``Raw:`` capture, CSV/TSV).
        columns: ``"mx=NAME,my=NAME,mz=NAME[,t=NAME,…]"`` (or a dict) for a delimited file that
            is not a docs/tracks_and_inputs.md track; also accepted for a track, to rename its
            columns.
        unit: the magnetometer unit of such a file: ``uT``, ``nT``, ``mG``, ``G`` or ``counts``.
        skip_bad_rows: skip and count malformed rows (text); an autopilot log is always read to
            its last complete message (what was lost is in ``read_warnings``).
        compass: an autopilot log's compass instance from 0 (default: the one the autopilot
            uses first); refused for other recordings.
        topics: ROS bags only: topic names picking one topic per message type where the bag
            has several (``--topic``, repeatable).
    """
    path = Path(path)
    fmt = detect(path)
    try:
        columns = parse_columns(columns)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    if (columns is not None or unit is not None) and fmt in ("dataflash", "ulog", "raw",
                                                             "rosbag1", "rosbag2"):
        raise InputError(f"{path}: --columns/--unit apply to CSV/TSV files; this is a "
                         f"{fmt} recording with its own units")
    if topics and fmt not in ("rosbag1", "rosbag2"):
        raise InputError(f"{path}: --topic applies to ROS bags; this is a {fmt} recording")
    if compass is not None and fmt not in ("dataflash", "ulog"):
        raise InputError(f"{path}: --compass applies to autopilot logs (ArduPilot .bin, PX4 "
                         "ULog); this recording holds one magnetometer")
    if fmt in ("rosbag1", "rosbag2"):
        from .rosbag import read_rosbag

        track = read_rosbag(path, fmt, topics=topics)
    elif fmt == "dataflash":
        from .dataflash import read_dataflash

        track = read_dataflash(path, skip_bad_rows=skip_bad_rows, compass=compass)
    elif fmt == "ulog":
        from .ulog import read_ulog

        track = read_ulog(path, skip_bad_rows=skip_bad_rows, compass=compass)
    elif fmt == "raw":
        from .raw_capture import read_raw_capture
        from .detect import read_whole

        track = read_raw_capture(path, read_whole(path), skip_bad_rows=skip_bad_rows)
    elif columns is not None:
        from .columns import read_columns_file
        from .detect import read_whole

        text = read_whole(path).decode("utf-8", errors="replace")
        track = read_columns_file(path, text, columns, unit, skip_bad_rows=skip_bad_rows)
    elif fmt == "track":
        if unit is not None:
            parse_unit(unit)
            raise InputError(f"{path}: --unit needs --columns (a section-1 track declares its "
                             "unit in '# mag_unit:')")
        return Track.read(path, skip_bad_rows=skip_bad_rows)
    else:
        # Not a section-1 header: the track reader names what is missing; add the way out.
        try:
            return Track.read(path, skip_bad_rows=skip_bad_rows)
        except TrackError as exc:
            raise TrackError(f"{exc.reason} (not a streamcal track nor a log format streamcal "
                             "recognises; for another CSV/TSV give --columns mx=NAME,my=NAME,"
                             "mz=NAME[,t=NAME] and --unit)", exc.path, exc.line,
                             exc.column) from None
    track.path = path
    return track


def read_compasses(path, *, skip_bad_rows: bool = False) -> list[Track]:
    """Every compass of an autopilot log, one Track each in instance order (metadata
    ``compass_instance``); InputError for a recording of one magnetometer."""
    path = Path(path)
    fmt = detect(path)
    if fmt == "dataflash":
        from .dataflash import read_dataflash_compasses

        tracks = read_dataflash_compasses(path, skip_bad_rows=skip_bad_rows)
    elif fmt == "ulog":
        from .ulog import read_ulog_compasses

        tracks = read_ulog_compasses(path, skip_bad_rows=skip_bad_rows)
    else:
        raise InputError(f"{path}: --compass applies to autopilot logs (ArduPilot .bin, PX4 "
                         "ULog); this recording holds one magnetometer")
    for track in tracks:
        track.path = path
    return tracks


def autopilot_calibration(track: Track) -> "Calibration":
    """The autopilot's own calibration from a track read from a flight log: ArduPilot's
    ``param.COMPASS_*``, or PX4's ``param.CAL_MAGn_*`` of the magnetometer the track holds, with
    the strength of the autopilot's corrected field (``autopilot_field_uT``); these metadata
    survive ``convert``."""
    md = track.metadata
    where = str(track.path) if track.path else "track"
    field = md.get("autopilot_field_uT")
    ardupilot = {k[len("param."):]: float(v) for k, v in md.items()
                 if k.startswith("param.COMPASS_")}
    prefix = md.get("mag_cal_params")
    if not ardupilot and not prefix:
        raise InputError(f"{where}: no autopilot compass parameters in the metadata (ArduPilot "
                         "COMPASS_* from PARM messages, or PX4 CAL_MAGn_* matching the "
                         "magnetometer's device id)")
    if field is None:
        raise InputError(f"{where}: no autopilot_field_uT in the metadata")
    if ardupilot:
        instance = int(md.get("compass_params_index", md.get("compass_instance", 0)))
        return calibration_from_ardupilot(ardupilot, float(field),
                                          source=f"{where} (compass "
                                                 f"{md.get('compass_instance', 0)}) COMPASS_* "
                                                 "parameters", instance=instance,
                                          order=md.get("ardupilot_correction_order",
                                                       MOTOR_AFTER_MATRIX))
    undone = md.get("mag_calibration_undone", "")
    if undone.startswith("could not"):
        raise InputError(f"{where}: mx,my,mz are PX4's calibrated field ({undone}): its "
                         "calibration is already applied to them")
    params = {k[len("param."):]: float(v) for k, v in md.items() if k.startswith("param.")}
    return calibration_from_px4(params, float(field), prefix=prefix,
                                compensation_in_readings=md.get("mag_calibrated_by_px4") == "yes",
                                channels=[name for name in track.columns if track.has(name)],
                                source=f"{where} {prefix}* parameters",
                                rotation=px4_rotation(md))
