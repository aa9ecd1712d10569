"""Device sources for the service loop: blocks from an I²C MPU-9250 or a serial board, with
bring-up and reconnection that never give up (a service outlives unplugged cables).

Both adapters offer the same small interface to :class:`~streamcal.service.daemon.Service`:

- ``read()`` → a :class:`~streamcal.samples.SampleBlock`, or None when nothing arrived in
  time; raises :class:`SourceUnavailable` while the device does not answer (the loop backs off
  and calls ``read()`` again, which retries);
- ``finished`` — a replay (``fake:``) has served its whole track;
- ``sleep(s)`` — the source's notion of waiting (real time, scaled time, or none for a stepped fake);
- ``counters()`` — JSON-ready figures for the status line; ``close()``.
"""
from __future__ import annotations

import time

from ..errors import InputError
from ..inputs.track import Track

FAKE_PREFIX = "fake:"


class SourceUnavailable(Exception):
    """The device does not answer now; the message says what failed and what to check."""


class I2CBlocks:
    """An MPU-9250 on an I²C bus (``"1"``) or a fake bus replaying a track (``"fake:TRACK.csv"``).

    Args:
        spec: bus spec as for :func:`firmware_bridge.i2c_source.open_bus`.
        address: 0x68 or 0x69.
        block_size: samples per block (a block is shorter after ``block_timeout`` s).
        rate_hz: poll rate while no sample is ready (default: the driver's, twice the mag rate).
        speed: fake bus only: replay at this multiple of real time (None: as fast as read, with
            track time stepped by the reads — deterministic).
        fake_kwargs: passed to :class:`~firmware_bridge.fake_mpu9250.FakeMPU9250Bus` (faults…).
        read_track: fake bus only: ``(path) -> Track`` reading its track (default
            :meth:`Track.read <streamcal.inputs.track.Track.read>`; the CLI's skips bad rows
            with ``--skip-bad-rows``).

    A fake track is a µT track or a raw-count MPU-9250/AK8963 log (see
    :meth:`~firmware_bridge.fake_mpu9250.FakeMPU9250Bus.from_track`); anything else, and an
    unreadable file, is an :class:`~streamcal.errors.InputError` naming the file, at construction.
    """

    def __init__(self, spec: str, address: int = 0x68, *, block_size: int = 50,
                 rate_hz: float | None = None, block_timeout: float = 1.0,
                 speed: float | None = None, fake_kwargs: dict | None = None,
                 read_track=None):
        from firmware_bridge.ports import open_bus
        from firmware_bridge.mpu9250 import MPU9250

        if rate_hz is not None and not rate_hz > 0:
            raise InputError(f"--rate must be a positive number of Hz, got {rate_hz}")
        self.fake = isinstance(spec, str) and spec.startswith(FAKE_PREFIX)
        if speed is not None and not self.fake:
            raise InputError("--speed applies to --bus fake:TRACK.csv only")
        if speed is not None and not speed > 0:
            raise InputError(f"--speed must be positive, got {speed}")
        fake_kwargs = dict(fake_kwargs or {})
        if self.fake and speed is not None:
            fake_kwargs.setdefault("clock", lambda: speed * time.monotonic())
        self.bus = open_bus(spec, read_track=read_track or Track.read, **fake_kwargs)
        driver_kwargs = {}
        if self.fake:
            driver_kwargs["clock"] = self.bus.now
            driver_kwargs["sleep"] = (lambda s: None) if speed is None \
                else (lambda s: time.sleep(s / speed))
        self.driver = MPU9250(self.bus, address, init=False, **driver_kwargs)
        self.sleep = self.driver._sleep
        self.label = spec if self.fake else f"i2c:{int(spec)}:0x{address:02X}"
        self.description = (f"fake i2c replaying {spec[len(FAKE_PREFIX):]}" if self.fake
                            else f"i2c bus {int(spec)} addr 0x{address:02X}")
        # how the fake read the track (raw AK8963 counts, IMU served at rest…): part of the
        # provenance, so it goes into the description (logged at start, recorded as ``source``)
        self.notes = list(getattr(self.bus, "notes", []) if self.fake else [])
        if self.notes:
            self.description += " (" + "; ".join(self.notes) + ")"
        self.block_size, self.block_timeout = int(block_size), float(block_timeout)
        self.poll_s = None if rate_hz is None else 1.0 / rate_hz
        self.up = False
        self.down = False
        self.bringups = 0
        self.outages = 0

    @property
    def finished(self) -> bool:
        return self.bus is None or bool(getattr(self.bus, "finished", False))

    def read(self):
        from firmware_bridge.mpu9250 import DeviceError

        try:
            if not self.up:
                self.driver.init()     # WHO_AM_I, reset, ranges, bypass, AK8963 fuse ROM
                self.up = True
                self.bringups += 1
            block = self.driver.read_block(self.block_size, timeout=self.block_timeout,
                                           source=self.label, poll_s=self.poll_s)
            self.down = False
        except DeviceError as exc:    # includes DeviceIOError and WrongDeviceError
            if not self.down:
                self.down = True
                self.outages += 1
            # The driver starts its next call with a health check and re-initialises a chip that
            # came back at its reset defaults; a failed bring-up is simply tried again.
            raise SourceUnavailable(str(exc)) from exc
        return block if len(block) else None

    def counters(self) -> dict:
        s = self.driver.stats
        return {"samples": s["samples"], "retries": s["retries"], "bus_errors": s["failures"],
                "nacks": s["nacks"], "overflows": s["overflows"], "overruns": s["overruns"],
                "reinits": s["reinits"], "outages": self.outages}

    def close(self) -> None:
        """Power the AK8963 down (best effort) and close the bus; safe to call twice."""
        if self.bus is None:
            return
        bus, self.bus = self.bus, None
        try:
            if self.up:
                self.driver.close()
        except Exception:        # closing must not turn a clean stop into a crash
            pass
        finally:
            close = getattr(bus, "close", None)
            if close is not None:
                close()


class SerialBlocks:
    """The ``streamcal_bridge`` board (or a MotionCal-style ``Raw:`` sketch) on a serial port.

    ``spec``: device path, pyserial URL or ``fake:TRACK.csv``; ``link``: an already open
    :class:`~firmware_bridge.serial_link.SerialLink` (tests). A port that fails (USB unplugged)
    is closed and reopened on later reads. ``read_track``: as for :class:`I2CBlocks`.
    ``board_options``: for a simulated board (``speed``: multiple of real time, None as fast as
    the host reads; fake: boards only).
    """

    def __init__(self, spec: str | None = None, baud: int = 115200, *, link=None,
                 block_size: int = 256, timeout: float = 0.2, read_track=None,
                 board_options: dict | None = None):
        self.spec, self.baud = spec, int(baud)
        self.board_options = dict(board_options or {})
        self.read_track = read_track or Track.read
        self.block_size, self.timeout = int(block_size), float(timeout)
        self.link = link
        self.sleep = time.sleep
        self.outages = 0
        self.reopens = 0
        if link is None:
            self._open()          # a wrong device path is a usage error at start (exit 2)
        source = spec or getattr(link, "source", "serial")
        self.description = f"serial {source}"

    def _open(self) -> None:
        from firmware_bridge.ports import open_link

        self.link = open_link(self.spec, self.baud, read_track=self.read_track,
                              **self.board_options)
        self.reopens += 1

    @property
    def finished(self) -> bool:
        board = getattr(self.link, "board", None)
        if board is None or not board.finished.is_set():
            return False
        if self._after_replay(board):
            return True
        # the board is finished once its last byte is written to the pty; on a loaded machine
        # those bytes can still wait in the pty for the host, so a replay ends only when the
        # port is empty too
        try:
            waiting = getattr(self.link.port, "in_waiting", 0) or 0
        except OSError:        # serial.SerialException is one: a failed port has nothing to come
            waiting = 0
        return not self.link.has_pending() and not waiting

    @staticmethod
    def _after_replay(board) -> bool:
        """A simavr board keeps sampling its (now frozen) sensor after the replay: once it is
        finished, what follows is not part of the track."""
        return bool(getattr(board, "streams_after_replay", False)) and board.finished.is_set()

    def read(self):
        import serial

        if self.link is None:
            try:
                self._open()
            except InputError as exc:
                raise SourceUnavailable(str(exc)) from exc
        board = getattr(self.link, "board", None)
        if board is not None and self._after_replay(board):
            return None
        try:
            return self.link.read_block(self.block_size, timeout=self.timeout)
        except (serial.SerialException, OSError) as exc:
            self.outages += 1
            link, self.link = self.link, None
            try:
                link.close()
            except Exception:
                pass
            if self.spec is None or self.spec.startswith((FAKE_PREFIX, "simavr:")):
                raise SourceUnavailable(f"serial port failed: {exc}") from exc
            raise SourceUnavailable(f"serial port {self.spec} failed ({exc}); reopening") from exc

    def counters(self) -> dict:
        if self.link is None:
            return {"outages": self.outages}
        s = self.link.stats
        return {"frames": s.frames, "samples": s.samples, "lost": s.lost,
                "crc_errors": s.crc_errors, "cobs_errors": s.cobs_errors,
                "truncated": s.truncated, "garbage_bytes": s.garbage_bytes,
                "raw_lines": s.raw_lines, "bad_lines": s.bad_lines, "dropped": s.dropped,
                "restarts": s.restarts,
                "outages": self.outages}

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
