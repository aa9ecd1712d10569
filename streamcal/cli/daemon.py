"""``streamcal daemon --bus N``: the Raspberry Pi service over I²C (docs/cli.md).

MPU-9250 on ``/dev/i2c-N`` (smbus2) → streaming calibrator (fits off the ingest path) →
``STATE_DIR/calibration.json`` (docs/calibration_file.md; atomic, with history) and calibrated
samples as JSON lines on a UNIX socket and/or stdout (format: :mod:`streamcal.service.output`).
Runs under systemd with ``Type=notify`` (``tools/streamcal-daemon.service``); SIGTERM/SIGINT
stop it cleanly (exit 0), SIGHUP re-reads the calibration file. Events go to stderr (the
journal), with the terminal coverage map at each coverage milestone unless ``--json-lines``.
``--bus fake:TRACK.csv`` runs the same code against a simulated MPU-9250 replaying a track.
"""
from __future__ import annotations

import json
import os
import sys

from ..calibration import DEFAULT_MODEL, jsonable
from ._common import add_skip_bad_rows

DEFAULT_STATE_DIR = "~/.local/state/streamcal"
SOCKET_NAME = "samples.sock"


def register(sub) -> None:
    p = sub.add_parser("daemon", help="the Raspberry Pi calibration service over I2C",
                       description="Read the MPU-9250 over I2C, calibrate continuously, keep the "
                                   "calibration in the state directory and serve calibrated "
                                   "samples (systemd Type=notify service).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--bus", metavar="N|fake:TRACK.csv",
                     help="I2C bus number (1 for /dev/i2c-1) or fake:TRACK.csv (simulated sensor)")
    src.add_argument("--port", metavar="mavlink:CONNECTION",
                     help="a flight controller over MAVLink: mavlink:udpin:HOST:PORT, "
                          "mavlink:tcp:HOST:PORT or mavlink:DEVICE[,BAUD] (docs/robots.md)")
    add_mavlink_options(p)
    p.add_argument("--address", default="0x68", type=_address,
                   help="MPU-9250 address: 0x68 (AD0 low, default) or 0x69")
    add_service_options(p)
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="poll rate while waiting for a sample (default: twice the 100 Hz mag rate)")
    add_speed_option(p, "--bus fake:…")
    add_skip_bad_rows(p)   # of a --bus fake: replay's track
    p.set_defaults(func=run)


def add_mavlink_options(p) -> None:
    """``--compass`` (the MAVLink magnetometer of ``--port mavlink:…``)."""
    p.add_argument("--compass", type=int, choices=(0, 1, 2), default=0,
                   help="with --port mavlink:…: the magnetometer read, 0 RAW_IMU (default), "
                        "1 SCALED_IMU2, 2 SCALED_IMU3")


def live_source(args, *, baud: int = 115200):
    """The source of ``--port mavlink:…`` (a :class:`~streamcal.service.mavlink_blocks.
    MavlinkBlocks`), or None for another ``--port``."""
    from ..service.mavlink_blocks import MavlinkBlocks, is_mavlink

    if not is_mavlink(getattr(args, "port", None)):
        return None
    return MavlinkBlocks(args.port, compass=args.compass, baud=baud)


def add_speed_option(p, device: str) -> None:
    p.add_argument("--speed", type=float, metavar="X",
                   help=f"with {device}: replay at X times the recorded pace (default: the "
                        "recorded pace with --http, else as fast as it can be read)")


def add_service_options(p) -> None:
    """Options shared with ``streamcal serial``."""
    p.add_argument("--state-dir", metavar="DIR",
                   help="calibration.json and its history (default: $STATE_DIRECTORY under "
                        f"systemd, else {DEFAULT_STATE_DIR})")
    p.add_argument("--socket", metavar="PATH",
                   help=f"UNIX stream socket serving calibrated samples as JSON lines (default: "
                        f"STATE_DIR/{SOCKET_NAME})")
    p.add_argument("--no-socket", action="store_true", help="do not open the sample socket")
    p.add_argument("--socket-mode", default="0660", type=lambda s: int(s, 8),
                   help="permissions of the socket file, octal (default: %(default)s)")
    p.add_argument("--json-lines", action="store_true",
                   help="also write calibrated samples as JSON lines on stdout")
    p.add_argument("--max-seconds", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--model", default=",".join(DEFAULT_MODEL),
                   help="comma-separated effects fitted (default: %(default)s)")
    p.add_argument("--sync-fits", action="store_true",
                   help="fit inline instead of on a worker thread (reproducible replays)")
    p.add_argument("--grace", type=float, default=10.0, metavar="S",
                   help="on stop, wait this long for the fit in flight (default: %(default)s)")
    add_http_options(p)


def add_http_options(p, when: str = "") -> None:
    """``--http``, ``--http-token`` and the place of the page's local field (``--lat``…)."""
    from ._location import add_location_options

    p.add_argument("--http", metavar="[HOST:]PORT",
                   help=when + "serve a read-only live page of the calibration (127.0.0.1 "
                        "unless HOST is given; see docs/live_page.md)")
    p.add_argument("--http-token", metavar="TOKEN",
                   help="with --http: require ?token=TOKEN (or an X-Streamcal-Token header)")
    add_location_options(p)


def _address(text: str) -> int:
    from ..errors import InputError

    try:
        value = int(text, 0)
    except ValueError:
        raise InputError(f"--address: expected 0x68 or 0x69, got {text!r}") from None
    if value not in (0x68, 0x69):
        raise InputError(f"--address: the MPU-9250 answers at 0x68 (AD0 low) or 0x69 (AD0 high), "
                         f"got 0x{value:02X}")
    return value


#: The column groups of the MPU-9250 stream beside the field (:func:`streamcal.model.stream_columns`).
SENSOR_GROUPS = ("temp", "accel", "gyro")


def _covariates(model) -> tuple:
    """Columns the coverage buffer keeps beside the field for ``model``'s effects (their
    declared needs)."""
    from ..errors import MissingColumnsError, UnknownEffectError
    from ..model import EFFECT_NAMES, stream_columns

    unknown = [m for m in model if m not in EFFECT_NAMES]
    if unknown or not model:
        raise UnknownEffectError(f"--model: unknown effect(s) {unknown or model}; known: "
                                 f"{', '.join(EFFECT_NAMES)}")
    try:
        return stream_columns(model, SENSOR_GROUPS)
    except MissingColumnsError as exc:
        raise UnknownEffectError(f"--model: {exc}") from None


def state_dir(args) -> str:
    if args.state_dir:
        return args.state_dir
    from_systemd = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return from_systemd or os.path.expanduser(DEFAULT_STATE_DIR)


def build(args, source, name: str, on_calibration=None):
    """The :class:`~streamcal.service.Service` for parsed ``args`` and an opened ``source``."""
    from ..errors import InputError
    from ..service import Outputs, Service, SocketOutput, StreamOutput
    from ..stream import CalibrationStore, CoverageBuffer, StreamingCalibrator

    if args.max_seconds is not None and not args.max_seconds > 0:
        raise InputError(f"--max-seconds must be positive, got {args.max_seconds}")
    model = tuple(m.strip() for m in args.model.split(",") if m.strip())
    covariates = _covariates(model)
    store = CalibrationStore(state_dir(args))

    def make_calibrator(buffer=None):
        return StreamingCalibrator(store=store, model=model, unit="uT",
                                   buffer=buffer if buffer is not None
                                   else CoverageBuffer(covariates=covariates),
                                   synchronous=args.sync_fits)

    sinks = []
    if args.json_lines:
        sinks.append(StreamOutput(sys.stdout))
    if not args.no_socket:
        sinks.append(SocketOutput(args.socket or os.path.join(store.dir, SOCKET_NAME),
                                  mode=args.socket_mode))
    observers = [live_page(args, name, lingers=_replayed(args))] \
        if getattr(args, "http", None) else []
    return Service(make_calibrator, source, outputs=Outputs(sinks), on_calibration=on_calibration,
                   on_coverage=None if args.json_lines else show_coverage,
                   max_seconds=args.max_seconds, grace_s=args.grace, name=name,
                   observers=observers)


def _replayed(args) -> bool:
    """A ``fake:`` or ``simavr:`` device: its page stays up after the replay (_live_replay)."""
    spec = str(getattr(args, "bus", None) or getattr(args, "port", None) or "")
    return spec.startswith(("fake:", "simavr:"))


def live_page(args, name: str, lingers: bool = False):
    """Start the ``--http`` page; returns the service observer feeding it (closing it stops
    the server, unless it ``lingers`` after a replay: then ``close_page`` does)."""
    from ..service.http_page import LivePage, is_loopback, parse_http
    from ..service.live_state import LiveState

    host, port = parse_http(args.http)
    if not is_loopback(host):
        print(f"streamcal {name}: warning: --http {args.http} listens beyond this machine; "
              + ("requests must carry the --http-token" if args.http_token else
                 "anyone who can reach it sees the calibration (add --http-token, or use an "
                 "SSH tunnel: docs/live_page.md)"), file=sys.stderr, flush=True)
    from ._location import location_reference

    state = LiveState(reference=location_reference(args))
    page = LivePage(state, host, port, token=args.http_token).start()
    print(f"streamcal {name}: live page at {page.url}", file=sys.stderr, flush=True)
    return _PageObserver(state, page, lingers)


def replay_page(args, calibrator):
    """``replay --realtime --http``: the page fed from the replay loop (a
    :class:`~streamcal.service.replay_feed.ReplayFeed` to call per block), or None without
    ``--http``."""
    from ..errors import InputError
    from ..service.replay_feed import ReplayFeed

    if not getattr(args, "http", None):
        return None
    if not args.realtime:
        raise InputError("--http needs --realtime (a replay at full speed is over before a "
                         "page could follow it)")
    return ReplayFeed(calibrator, [live_page(args, "replay", lingers=True)])


class _PageObserver:
    """The :class:`~streamcal.service.live_state.LiveState` observer that also stops the page."""

    def __init__(self, state, page, lingers: bool = False):
        self.state, self.page, self.lingers = state, page, lingers
        self.on_block, self.on_events = state.on_block, state.on_events

    def close(self) -> None:
        if not self.lingers:
            self.close_page()

    def close_page(self) -> None:
        self.state.close()
        self.page.close()


def show_coverage(calibrator) -> None:
    """The terminal map of the sphere at a coverage milestone, on stderr after the event line
    (stdout may carry samples or the summary), as ``streamcal replay`` draws it."""
    from ..report.terminal import coverage_view

    print(coverage_view(calibrator.buffer), file=sys.stderr, flush=True)


def run(args) -> int:
    import time

    from ..service import I2CBlocks

    from ..errors import InputError
    from ._common import fake_track_reader
    from ._live_replay import TrackSpan, announce, replay_speed, serve_after_replay

    from ._location import location_reference

    location_reference(args)    # a mistyped --lat/--date said before the device is opened
    started = time.monotonic()
    span = TrackSpan(fake_track_reader(args))
    spec = args.bus if args.bus is not None else args.port
    speed = replay_speed(args, spec)
    if args.port is not None:
        if args.rate is not None:
            raise InputError("--rate applies to --bus (a flight controller sets its own stream "
                             "rates)")
        source = live_source(args)
        if source is None:
            raise InputError(f"--port {args.port}: the daemon's --port is a flight controller, "
                             "mavlink:CONNECTION (the Arduino board runs under streamcal serial)")
    else:
        source = I2CBlocks(args.bus, args.address, rate_hz=args.rate, speed=speed,
                           read_track=span)
    try:
        service = build(args, source, "daemon")
    except BaseException:
        source.close()
        raise
    announce(args, "daemon", spec, speed, span)
    service.install_signal_handlers()
    code = service.run()
    print(json.dumps(jsonable(service.summary()), allow_nan=False), file=sys.stderr if args.json_lines else sys.stdout,
          flush=True)
    serve_after_replay(service, "daemon", args.max_seconds, started)
    return code
