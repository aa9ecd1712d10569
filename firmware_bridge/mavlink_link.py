"""A flight controller's MAVLink telemetry → :class:`SampleBlock`, decoded by pymavlink.

``MavlinkLink("udpin:127.0.0.1:14550")`` listens where the autopilot (or MAVProxy's
``--out``) sends; any pymavlink connection string works: ``udpin:HOST:PORT``, ``udp:…``,
``tcp:HOST:PORT``, or a serial device (``/dev/ttyACM0``, with ``,BAUD`` to set the rate).
Messages read (units as in MAVLink's common.xml):

================== ================================================ ========================
``RAW_IMU``        xmag..zmag mgauss; xacc.. mG, xgyro.. mrad/s        compass 0 (``--compass 0``)
``SCALED_IMU2``    the same fields, scaled                            compass 1
``SCALED_IMU3``    the same fields, scaled                            compass 2
``SCALED_PRESSURE`` temperature cdegC                                 ``temp`` °C
``BATTERY_STATUS`` current_battery cA (−1: not measured), battery 0   ``battery_current_a`` A
``ATTITUDE``       roll, pitch, yaw rad                               ``attitude_roll``.. rad
``HEARTBEAT``      counted; its autopilot type decides RAW_IMU's IMU units
================== ================================================ ========================

1 mgauss = 0.1 µT; 1 mG = 9.80665e-3 m/s²; 1 mrad/s = 1e-3 rad/s. ``RAW_IMU`` carries the
sensor's raw units except on ArduPilot, which fills it exactly like ``SCALED_IMU`` (common.xml):
its accelerometer and gyro are used only once a heartbeat says the autopilot is ArduPilot; its
magnetometer is always read as mgauss. Only the selected compass's message gives rows with
``mx,my,mz`` (and that message's IMU fields), and only from the first vehicle (system id)
heard; the others are ignored.

Time is the vehicle's (``time_usec``/``time_boot_ms`` since boot, in s); ``BATTERY_STATUS``,
which has no stamp, takes the latest vehicle time seen. Lost messages are counted from the
MAVLink sequence numbers (pymavlink's ``mav_loss``), garbage from its ``BAD_DATA``. A link
silent for ``silence_s`` raises :class:`MavlinkSilent`; a connection that fails (a serial device
unplugged, a TCP peer gone) is closed and opened again on the next read.
"""
from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, fields

import numpy as np

from streamcal.errors import InputError, StreamcalError
from streamcal.samples import SampleBlock

MAVLINK_PREFIX = "mavlink:"
COMPASS_MESSAGES = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
UT_PER_MGAUSS = 0.1
MPS2_PER_MG = 9.80665e-3
RAD_S_PER_MRAD_S = 1e-3
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
AUX_CHANNELS = ("battery_current_a", "attitude_roll", "attitude_pitch", "attitude_yaw")
_EPOCH_USEC = 10**15      # common.xml: time_usec above this is UNIX time, below it since boot
_REBOOT_S = 1.0
_MAV_AUTOPILOT_INVALID = 8
_LISTENING = ("udpin:", "udp:", "udpbcast:")
_WANTED = set(COMPASS_MESSAGES) | {"SCALED_PRESSURE", "BATTERY_STATUS", "ATTITUDE",
                                   "HEARTBEAT"}


class MavlinkSilent(StreamcalError):
    """No (usable) message for a while; the message says what arrived and what to check."""


@dataclass
class MavlinkStats:
    """What arrived and what was lost. ``lost``: messages missing from the senders' sequence
    numbers; ``bad_data``/``garbage_bytes``: what pymavlink could not parse, or parsed as a
    message id it does not know; ``link_drops``:
    times the link fell silent or failed; ``reconnects``: connections opened after the first;
    ``other_vehicles``: compass messages of another system id than the first one heard
    (ignored)."""

    messages: int = 0
    heartbeats: int = 0
    lost: int = 0
    bad_data: int = 0
    garbage_bytes: int = 0
    mag_samples: int = 0
    other_vehicles: int = 0
    link_drops: int = 0
    reconnects: int = 0

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def parse_connection(spec: str) -> tuple[str, int | None]:
    """``mavlink:CONNECTION`` (or ``CONNECTION``) → (pymavlink connection string, baud or None):
    a serial device may end in ``,BAUD``."""
    conn = spec[len(MAVLINK_PREFIX):] if spec.startswith(MAVLINK_PREFIX) else spec
    if not conn:
        raise InputError("mavlink: needs a connection, e.g. mavlink:udpin:127.0.0.1:14550, "
                         "mavlink:tcp:127.0.0.1:5760 or mavlink:/dev/ttyACM0,115200")
    match = re.fullmatch(r"(/[^,:]+),(\d+)", conn)
    if match:
        return match.group(1), int(match.group(2))
    return conn, None


class MavlinkLink:
    """Blocks of samples from one MAVLink connection (see the module docstring).

    Args:
        spec: ``mavlink:CONNECTION`` or a bare pymavlink connection string.
        compass: 0 (``RAW_IMU``), 1 (``SCALED_IMU2``) or 2 (``SCALED_IMU3``).
        baud: serial rate when ``spec`` does not give one.
        silence_s: seconds without the selected compass's message before :meth:`read_block`
            raises :class:`MavlinkSilent`.
    """

    def __init__(self, spec: str, *, compass: int = 0, baud: int = 115200,
                 silence_s: float = 3.0):
        if compass not in range(len(COMPASS_MESSAGES)):
            raise InputError(f"--compass: 0 (RAW_IMU), 1 (SCALED_IMU2) or 2 (SCALED_IMU3), "
                             f"got {compass}")
        self.connection, given_baud = parse_connection(spec)
        self.baud = given_baud or int(baud)
        self.compass = COMPASS_MESSAGES[compass]
        self.silence_s = float(silence_s)
        self.source = f"mavlink:{self.connection}"
        self.stats = MavlinkStats()
        self.autopilot: int | None = None
        self.vehicle: int | None = None      # MAVLink system id whose compass is read
        self.seen: dict[str, int] = {}
        self.conn = None
        self._loss_base = 0           # mav_loss of the connections closed so far
        self._opened = 0
        self._t_vehicle: float | None = None
        self._t_last: float | None = None
        self._last_compass = time.monotonic()
        self._down = False
        self.open()     # a bad connection string or a missing device: InputError at start

    # -- connection ---------------------------------------------------------------------------
    def open(self) -> None:
        from pymavlink import mavutil

        try:
            self.conn = mavutil.mavlink_connection(self.connection, baud=self.baud,
                                                   source_system=255, source_component=190,
                                                   robust_parsing=True, autoreconnect=False,
                                                   retries=0)
        except Exception as exc:   # socket.gaierror, serial.SerialException, ValueError…
            raise InputError(f"{self.source}: cannot open the MAVLink connection "
                             f"({type(exc).__name__}: {exc})") from None
        if hasattr(self.conn, "handle_eof"):
            # pymavlink's TCP link prints and carries on at a closed peer; here it is a failure
            # that read_block turns into a reconnection
            def peer_closed():
                raise ConnectionError("the TCP peer closed the connection")

            self.conn.handle_eof = self.conn.handle_disconnect = peer_closed
        port = getattr(self.conn, "port", None)
        if self.connection.startswith(_LISTENING) and hasattr(port, "setsockopt"):
            import socket

            try:    # room for a few seconds of telemetry while the reader is busy (capped by
                port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)  # rmem_max)
            except OSError:
                pass
        if self._opened:
            self.stats.reconnects += 1
        self._opened += 1
        self._last_compass = time.monotonic()

    def close(self) -> None:
        if self.conn is not None:
            conn, self.conn = self.conn, None
            self._loss_base += int(getattr(conn, "mav_loss", 0))
            try:
                conn.close()
            except Exception:      # closing a failed port must not turn into a crash
                pass

    @property
    def up(self) -> bool:
        return self.conn is not None and not self._down

    def _drop(self, why: str) -> MavlinkSilent:
        if not self._down:
            self._down = True
            self.stats.link_drops += 1
        return MavlinkSilent(why)

    # -- reading ------------------------------------------------------------------------------
    def read_block(self, max_samples: int = 50, timeout: float = 0.2) -> SampleBlock | None:
        """Rows decoded within ``timeout`` s (at most ``max_samples`` compass rows), or None.

        Raises:
            MavlinkSilent: the selected compass has been silent for ``silence_s`` s, or the
                connection failed (it is reopened by the next call).
        """
        if self.conn is None:
            try:
                self.open()
            except InputError as exc:
                raise self._drop(str(exc)) from None
        rows: list[tuple] = []
        mag_rows = 0
        end = time.monotonic() + timeout
        while mag_rows < max_samples:
            left = end - time.monotonic()
            if left <= 0:
                break
            try:
                msg = self.conn.recv_match(blocking=True, timeout=min(left, 0.05))
            except (OSError, ConnectionError) as exc:   # serial.SerialException is an OSError
                self.close()
                raise self._drop(f"{self.source} failed ({exc}); reopening") from None
            if msg is None:
                continue
            row = self._row(msg)
            if row is not None:
                rows.append(row)
                mag_rows += row[0] == "mag"
        self.stats.lost = self._loss_base + int(getattr(self.conn, "mav_loss", 0))
        if mag_rows:
            self._last_compass = time.monotonic()
            if self._down:
                self._down = False
        elif time.monotonic() - self._last_compass > self.silence_s:
            why = self._silence_text()
            if not self.connection.startswith(_LISTENING):
                self.close()                         # TCP or serial: reconnect on the next read
                why += "; reconnecting"
            raise self._drop(why)
        return self._block(rows) if rows else None

    def _silence_text(self) -> str:
        busiest = sorted(self.seen.items(), key=lambda item: (-item[1], item[0]))[:8]
        others = ", ".join(f"{name} {count}" for name, count in busiest)
        if others:
            hint = f"messages so far: {others}"
            if any(name in self.seen for name in COMPASS_MESSAGES if name != self.compass):
                hint += " (another compass: see --compass)"
        else:
            hint = "no MAVLink message so far: check the connection and the autopilot's stream rates"
        return f"no {self.compass} for {self.silence_s:g} s on {self.source}; {hint}"

    def _row(self, msg):
        """``(kind, t, values)`` for a message that gives a row, else None (counted)."""
        kind = msg.get_type()
        if kind == "BAD_DATA" or msg.get_msgId() < 0:
            # unparsable bytes, or an id this dialect does not know (its CRC cannot be checked:
            # often garbage that looked like a frame); the sequence numbers skip them too
            self.stats.bad_data += 1
            self.stats.garbage_bytes += len(getattr(msg, "data", b"") or b"")
            return None
        self.stats.messages += 1          # every message, as the sequence numbers count them
        self.seen[kind] = self.seen.get(kind, 0) + 1
        if kind not in _WANTED:
            return None
        if kind == "HEARTBEAT":
            self.stats.heartbeats += 1
            # a ground station's heartbeat (MAV_AUTOPILOT_INVALID) says nothing of the vehicle
            if msg.autopilot != _MAV_AUTOPILOT_INVALID and (
                    self.vehicle is None or msg.get_srcSystem() == self.vehicle):
                self.autopilot = int(msg.autopilot)
            return None
        if kind in COMPASS_MESSAGES:
            if kind != self.compass:
                return None
            if self.vehicle is None:
                self.vehicle = msg.get_srcSystem()      # the first vehicle heard is the one read
            elif msg.get_srcSystem() != self.vehicle:
                self.stats.other_vehicles += 1
                return None
            t = msg.time_usec * 1e-6 if kind == "RAW_IMU" else msg.time_boot_ms * 1e-3
            if kind == "RAW_IMU" and msg.time_usec > _EPOCH_USEC:
                t = self._t_vehicle if self._t_vehicle is not None else 0.0
            self._t_vehicle = t
            self.stats.mag_samples += 1
            mag = np.array([msg.xmag, msg.ymag, msg.zmag], dtype=np.float64) * UT_PER_MGAUSS
            imu = None
            if kind != "RAW_IMU" or self.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
                imu = (np.array([msg.xacc, msg.yacc, msg.zacc], dtype=np.float64) * MPS2_PER_MG,
                       np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=np.float64)
                       * RAD_S_PER_MRAD_S)
            return ("mag", t, (mag, imu))
        if kind == "BATTERY_STATUS":
            if msg.id != 0 or msg.current_battery == -1 or self._t_vehicle is None:
                return None
            return ("aux", self._t_vehicle, {"battery_current_a": msg.current_battery * 0.01})
        t = msg.time_boot_ms * 1e-3
        self._t_vehicle = t if self._t_vehicle is None else max(self._t_vehicle, t)
        if kind == "SCALED_PRESSURE":
            return ("temp", t, msg.temperature * 0.01)
        return ("aux", t, {"attitude_roll": msg.roll, "attitude_pitch": msg.pitch,
                           "attitude_yaw": msg.yaw})

    def _block(self, rows) -> SampleBlock:
        n = len(rows)
        t = np.array([r[1] for r in rows], dtype=np.float64)
        mag, accel, gyro = (np.full((n, 3), np.nan) for _ in range(3))
        temp = np.full(n, np.nan)
        aux = {name: np.full(n, np.nan) for name in AUX_CHANNELS}
        for i, (kind, _, values) in enumerate(rows):
            if kind == "mag":
                mag[i] = values[0]
                if values[1] is not None:
                    accel[i], gyro[i] = values[1]
            elif kind == "temp":
                temp[i] = values
            else:
                for name, value in values.items():
                    aux[name][i] = value if math.isfinite(value) else np.nan
        order = np.argsort(t, kind="stable")
        pick = lambda a: a[order]  # noqa: E731
        t = t[order]
        # a message stamped a little before the previous block's last row (streams interleave)
        # keeps time non-decreasing; a jump back of over a second is a reboot and passes
        if self._t_last is not None and t[0] >= self._t_last - _REBOOT_S:
            t = np.maximum(t, self._t_last)
        self._t_last = float(t[-1])
        return SampleBlock(t=t, mag=pick(mag), accel=pick(accel), gyro=pick(gyro),
                           temp=pick(temp), aux={k: pick(v) for k, v in aux.items()},
                           source=self.source)
