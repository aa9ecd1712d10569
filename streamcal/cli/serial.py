"""``streamcal serial --port DEV``: host side of the Arduino sketch (docs/cli.md).

Frames from the ``streamcal_bridge`` sketch (or the ``Raw:`` lines of MotionCal-style sketches,
detected automatically) → streaming calibrator → ``STATE_DIR/calibration.json``. Each accepted
calibration (and the one loaded at start) is sent back to the board, which keeps it in EEPROM and
streams calibrated directions; the board's answer is reported. Calibrated samples as in
``streamcal daemon`` (socket and/or ``--json-lines``); events and, unless ``--json-lines``, the
terminal coverage map at each coverage milestone on stderr. At the end the frames are accounted for:
received + lost (from the board's sequence numbers) = sent. ``--port fake:TRACK.csv`` runs
against a simulated board on a pseudo-terminal; ``--port simavr:TRACK.csv`` runs the compiled
sketch itself in simavr (firmware in the loop; needs the AVR toolchain and simavr). When the
sketch calibrates itself (SELF_CAL frames), its latest fit is shown beside the host's calibration
with which one the board has in force and why (``board_self_cal`` in the summary).
"""
from __future__ import annotations

import json
import sys

from ..calibration import jsonable
from ._common import add_skip_bad_rows
from .daemon import add_service_options, add_speed_option, build
from ._selfcal import board_self_cal, format_board_self_cal


def register(sub) -> None:
    p = sub.add_parser("serial", help="host side of the Arduino sketch (pyserial)",
                       description="Read the streamcal_bridge sketch (or MotionCal-style Raw: "
                                   "lines) over a serial port, calibrate continuously and send "
                                   "each accepted calibration back to the board.")
    p.add_argument("--port", required=True, metavar="DEV|fake:TRACK.csv|simavr:TRACK.csv",
                   help="serial device (/dev/ttyACM0), pyserial URL, fake:TRACK.csv (simulated "
                        "board) or simavr:TRACK.csv (the compiled sketch in simavr)")
    p.add_argument("--baud", type=int, default=115200, help="baud rate (default: %(default)s)")
    add_service_options(p)
    add_speed_option(p, "--port fake:…")
    add_skip_bad_rows(p)   # of a fake:/simavr: replay's track
    p.set_defaults(func=run)


class BoardSync:
    """``on_calibration`` hook: send the calibration in use to the board, report its answer."""

    def __init__(self, source):
        self.source = source
        self.sent: list[int] = []
        self.failures = 0
        self.offered = 0

    def __call__(self, cal, service) -> str | None:
        link = self.source.link
        if link is None:
            return None
        self.offered += 1
        if link.mode == "raw":
            return "board prints Raw: lines: it cannot take a calibration (kept on the host)"
        from firmware_bridge.serial_link import LinkError

        from ..errors import InputError

        try:
            cal_id = link.send_calibration(cal)
        except InputError as exc:
            self.failures += 1
            return f"calibration not sent to the board: {exc}"
        except (LinkError, OSError) as exc:
            self.failures += 1
            return f"board did not take the calibration: {exc}"
        self.sent.append(cal_id)
        return f"board acknowledged calibration id 0x{cal_id:04X} (stored in its EEPROM)"


def close_count(source) -> dict:
    """Ask the board what it holds (its answer is the last frame, closing the loss count) and
    return the frame accounting."""
    link = source.link
    out = {}
    if link is None:
        return out
    if link.mode == "frames":
        try:
            report = link.query_calibration(timeout=0.5, retries=5)
            out["board_calibration"] = {"valid": bool(report.valid), "cal_id": report.cal_id}
        except Exception as exc:    # the board may be gone: report, do not fail the run
            out["board_calibration"] = {"error": str(exc)}
    stats = link.stats
    out.update({"frames_received": link.sequence.received, "frames_lost": stats.lost,
                **{k: v for k, v in stats.as_dict().items() if v and k not in ("frames", "lost")}})
    sent = getattr(getattr(link, "board", None), "frames_sent", None)   # fake: boards count
    if sent is not None:
        out["frames_sent"] = sent
    return out


def run(args) -> int:
    import time

    from ..service import SerialBlocks

    from ._common import fake_track_reader
    from ._live_replay import TrackSpan, announce, replay_speed, serve_after_replay

    from ._location import location_reference

    location_reference(args)    # a mistyped --lat/--date said before the port is opened
    started = time.monotonic()
    span = TrackSpan(fake_track_reader(args))
    speed = replay_speed(args, args.port)
    source = SerialBlocks(args.port, args.baud, read_track=span,
                          board_options=None if speed is None else {"speed": speed})
    try:
        sync = BoardSync(source)
        service = build(args, source, "serial", on_calibration=sync)
    except BaseException:
        source.close()
        raise
    announce(args, "serial", args.port, speed, span)
    service.install_signal_handlers()
    source_close, source.close = source.close, lambda: None   # keep the port for the count
    try:
        code = service.run()
        frames = close_count(source)
    finally:
        source_close()
    summary = {**service.summary(), "link": frames, "sent_to_board": len(sync.sent)}
    board = board_summary(source, service, frames, sync)
    if board is not None:
        summary["board_self_cal"] = board
        if not args.json_lines:
            print(format_board_self_cal(board), flush=True)
    print(json.dumps(jsonable(summary), allow_nan=False), file=sys.stderr if args.json_lines else sys.stdout, flush=True)
    serve_after_replay(service, "serial", args.max_seconds, started)
    return code


def board_summary(source, service, frames: dict, sync: BoardSync) -> dict | None:
    """The board's own calibration beside the host's (None: the board sent no SELF_CAL frame)."""
    link = source.link
    if link is None:
        return None
    report = frames.get("board_calibration", {})
    board_id = report.get("cal_id") if report.get("valid") else None
    host = service.calibrator.calibration if service.calibrator is not None else None
    return board_self_cal(getattr(link, "self_cal", ()), host, board_id, sync.sent)
