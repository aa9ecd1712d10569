"""Host side of the ``streamcal_bridge`` sketch: frames from a serial port → :class:`SampleBlock`.

The port is injected (anything with pyserial's ``read/write/in_waiting/close``), so the same code
runs on a real board, on pyserial's ``loop://``, or on :class:`~firmware_bridge.fake_board.FakeBoard`
over a pty. :meth:`SerialLink.open` picks the transport from a string:

- ``fake:TRACK.csv`` — start a simulated board replaying the track and open its pty;
- ``simavr:TRACK.csv`` — the compiled sketch itself in simavr, its simulated MPU-9250/AK8963
  replaying the track (:class:`~firmware_bridge.simavr_board.SimavrBoard`; needs the AVR
  toolchain and simavr, HARDWARE.md §7), its UART on a pty;
- any pyserial URL (``loop://``, ``socket://host:port``, ``rfc2217://…``) or device path.

The link also reads the ``Raw:`` text lines of MotionCal-style sketches on the same port
(auto-detected, see :mod:`firmware_bridge.rawlines`). Single-threaded: commands wait for their
ACK by pumping the port, and samples that arrive meanwhile are kept, not dropped.

    link = SerialLink.open("/dev/ttyACM0")
    for block in link.blocks(idle_timeout=2.0):
        ...                       # block.mag (n,3) µT, block.accel m/s², block.gyro rad/s
    link.send_calibration(cal)    # K, b stored in the board's EEPROM, applied on the board
"""
from __future__ import annotations

import collections
import time
import zlib
from dataclasses import dataclass, fields
from typing import Iterator

import numpy as np

from streamcal.errors import InputError, StreamcalError

from . import frames as fr
from .rawlines import RawLineReader, raw_to_si
from streamcal.samples import SampleBlock

DEFAULT_BAUD = 115200
_READ_CHUNK = 4096
_MODES = ("auto", "frames", "raw")


class LinkError(StreamcalError):
    """The board did not answer, or refused a command; names the command and the reason."""

    exit_code = 2


@dataclass
class LinkStats:
    """What arrived and what was lost. ``lost`` counts frames missing from the board's sequence
    numbers (so ``received + lost`` = frames the board sent, up to the last one received; a
    board restart begins a new count). ``restarts``: board reboots seen (a HELLO with sequence
    number 0 after other frames: brown-out, watchdog, a DTR reset)."""

    frames: int = 0
    samples: int = 0
    lost: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    truncated: int = 0
    oversized: int = 0
    malformed: int = 0
    garbage_bytes: int = 0
    unexpected: int = 0       # host→board frames seen on the line (e.g. loop:// echo)
    mag_overflows: int = 0
    i2c_errors: int = 0
    retries: int = 0
    naks: int = 0
    raw_lines: int = 0
    bad_lines: int = 0
    dropped: int = 0          # samples dropped because nobody read them (bounded queue)
    restarts: int = 0         # board reboots (its sequence numbers and µs clock restarted)

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class SerialLink:
    """Frames in, sample blocks out; commands with ACK and retry.

    ``port``: an open pyserial-like object; ``source``: the name put in each block;
    ``mode``: ``"auto"`` (detect binary frames or ``Raw:`` lines), ``"frames"`` or ``"raw"``;
    ``max_pending``: samples kept when nobody reads (oldest dropped and counted beyond).
    """

    def __init__(self, port, *, source: str = "serial", mode: str = "auto", board=None,
                 max_pending: int = 100_000):
        if mode not in _MODES:
            raise InputError(f"serial mode {mode!r}: expected one of {', '.join(_MODES)}")
        self.port = port
        self.source = source
        self.mode = mode
        self.board = board
        self.hello: fr.Hello | None = None
        self.sphere_sums: fr.SphereSums | None = None
        #: the board's own calibration: its SELF_CAL frames, oldest first (bounded)
        self.self_cal: collections.deque = collections.deque(maxlen=256)
        self.sequence = fr.SequenceCounter()
        self._decoder = fr.FrameDecoder()
        self._raw = RawLineReader()
        self._stats = LinkStats()
        self._pending = collections.deque()     # (kind, row) kind "s" Sample / "r" raw (t, 9 counts)
        self._cal = collections.deque(maxlen=max_pending)   # (t_us, x0, x1, x2)
        self._answers: list[fr.Frame] = []
        self._max_pending = max_pending
        self._seq = 0
        self._t_wrap = 0
        self._t_last: int | None = None
        self._t0 = time.monotonic()

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    def open(cls, spec: str, baud: int = DEFAULT_BAUD, *, timeout: float = 0.05, mode: str = "auto",
             board=None, source: str | None = None) -> "SerialLink":
        """Open ``spec`` (a pyserial URL or a device path) and wake the board. Simulated boards
        (``fake:``, ``simavr:``) open through :func:`firmware_bridge.ports.open_link`, which
        passes the simulated ``board`` (closed with the link) and the ``source`` label."""
        import serial

        if spec.partition(":")[0] in ("fake", "simavr"):
            raise InputError(f"{spec}: simulated boards open through firmware_bridge.ports.open_link")
        target, open_port = spec, lambda: serial.serial_for_url(spec, baudrate=baud, timeout=timeout)
        try:
            port = open_port()
        except (serial.SerialException, ValueError, OSError) as exc:
            if board is not None:
                board.close()
            raise InputError(f"serial port {target!r}: cannot open ({exc})") from None
        link = cls(port, source=source or f"serial:{spec}", mode=mode, board=board)
        link.wake()
        return link

    def wake(self) -> None:
        """Flush the board's receiver (a bare delimiter) and ask for its HELLO."""
        self.port.write(fr.DELIMITER + self._frame(fr.GetInfo()))

    def close(self) -> None:
        try:
            self.port.close()
        finally:
            if self.board is not None:
                self.board.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- reading ------------------------------------------------------------------------------
    @property
    def stats(self) -> LinkStats:
        s = self._stats
        if self.mode != "raw":
            for name, value in self._decoder.stats.as_dict().items():
                if name != "frames":
                    setattr(s, name, value)
        s.lost = self.sequence.lost
        s.raw_lines, s.bad_lines = self._raw.stats.lines, self._raw.stats.bad_lines
        return s

    def pump(self) -> int:
        """Read what the port has (waiting up to the port's own timeout for the first byte),
        decode it, and queue the samples; return the number of bytes read."""
        # The port's timeout is set once at open: changing it reconfigures termios on each call.
        n = max(1, min(getattr(self.port, "in_waiting", 0) or 0, _READ_CHUNK))
        data = self.port.read(n)
        if data:
            self.feed(data)
        return len(data)

    def feed(self, data: bytes) -> None:
        """Decode bytes as if read from the port (the link's pure entry point)."""
        if self.mode in ("auto", "frames"):
            for frame in self._decoder.feed(data):
                self._on_frame(frame)
        if self.mode in ("auto", "raw"):
            rows = self._raw.feed(data)
            if len(rows):
                t = time.monotonic() - self._t0
                self._push([("r", (t, row)) for row in rows])
                if self.mode == "auto":
                    self.mode = "raw"

    def _on_frame(self, frame: fr.Frame) -> None:
        if frame.type not in fr.BOARD_TO_HOST:
            self._stats.unexpected += 1
            return
        if self.mode == "auto":
            self.mode = "frames"
        if isinstance(frame.msg, fr.Hello) and frame.seq == 0:
            self._on_boot()
        self.sequence.observe(frame.seq)
        self._stats.frames += 1
        msg = frame.msg
        if isinstance(msg, fr.Sample):
            self._stats.mag_overflows += bool(msg.status & fr.Status.MAG_OVERFLOW)
            self._stats.i2c_errors += bool(msg.status & fr.Status.I2C_ERROR)
            self._push([("s", msg)])
        elif isinstance(msg, fr.CalSample):
            self._cal.append((msg.t_us,) + tuple(msg.x))
        elif isinstance(msg, fr.SphereSums):
            self.sphere_sums = msg
        elif isinstance(msg, fr.SelfCal):
            self.self_cal.append(msg)
        elif isinstance(msg, fr.Hello):
            self.hello = msg
        else:
            self._answers.append(frame)
            del self._answers[:-64]

    def _on_boot(self) -> None:
        """A HELLO numbered 0: the board booted. Its sequence numbers start again (not a loss)
        and so does its µs clock. After other frames (not the first HELLO of the link, and not
        the sequence number wrapping round to 0 from 65535) this is a restart: counted, and
        the samples from here on are timed from the board's new clock (a mark in the queue,
        so the samples still waiting keep the old one)."""
        seq = self.sequence
        if seq.received and seq.expected != 0:
            self._stats.restarts += 1
            if not (self._pending and self._pending[-1][0] == "b"):
                self._push([("b", None)])
        seq.reset()

    def _restart_clock(self) -> None:
        """Forget the board clock's history: the next time unwraps from itself (board time
        restarts near 0; :class:`~streamcal.stream.StreamingCalibrator` keeps its time
        monotone across it)."""
        self._t_last, self._t_wrap = None, 0

    def _push(self, items) -> None:
        self._pending.extend(items)
        excess = len(self._pending) - self._max_pending
        for _ in range(max(0, excess)):
            if self._pending.popleft()[0] == "b":     # what came before the reboot is gone
                self._restart_clock()
            else:
                self._stats.dropped += 1

    def read_block(self, max_samples: int = 256, timeout: float = 0.1) -> SampleBlock | None:
        """Up to ``max_samples`` samples as one block, or None if none arrived within ``timeout`` s.

        Binary samples wait for the board's HELLO (it carries the scales); the link asks for it."""
        deadline = time.monotonic() + timeout
        asked = False
        while True:
            block = self._take(max_samples)
            if block is not None:
                return block
            if self._pending and self.hello is None and not asked:
                self.port.write(self._frame(fr.GetInfo()))
                asked = True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self.pump()

    def has_pending(self) -> bool:
        """Whether decoded samples are waiting for :meth:`read_block`."""
        pending = self._pending
        return bool(pending) and not (len(pending) == 1 and pending[0][0] == "b")

    def blocks(self, max_samples: int = 256, idle_timeout: float | None = None) -> Iterator[SampleBlock]:
        """Yield blocks as they arrive; stop after ``idle_timeout`` s without samples (None: never)."""
        last = time.monotonic()
        while True:
            block = self.read_block(max_samples, timeout=0.1)
            if block is not None:
                last = time.monotonic()
                yield block
            elif idle_timeout is not None and time.monotonic() - last >= idle_timeout:
                return

    def calibrated(self) -> tuple[np.ndarray, np.ndarray]:
        """Drain the board's calibrated output: t (n,) s (board clock) and x (n,3) unit-free."""
        rows = np.array(list(self._cal), dtype=float).reshape(-1, 4)
        self._cal.clear()
        return self._unwrap_times(rows[:, 0].astype(np.int64), advance=False), rows[:, 1:]

    def _take(self, max_samples: int) -> SampleBlock | None:
        while self._pending and self._pending[0][0] == "b":    # a reboot mark: new board clock
            self._pending.popleft()
            self._restart_clock()
        if not self._pending:
            return None
        kind = self._pending[0][0]
        if kind == "s" and self.hello is None:
            return None
        items = []
        while self._pending and len(items) < max_samples and self._pending[0][0] == kind:
            items.append(self._pending.popleft()[1])
        self._stats.samples += len(items)
        return self._frames_block(items) if kind == "s" else self._raw_block(items)

    def _frames_block(self, samples: list[fr.Sample]) -> SampleBlock:
        h = self.hello
        v = np.array([s.values() for s in samples], dtype=np.int64)  # t_us, mag3, accel3, gyro3, temp, status
        status = v[:, 11]
        def masked(cols, bit, scale):
            out = v[:, cols] * np.asarray(scale, dtype=float)
            out[(status & bit) == 0] = np.nan
            return out
        mag = masked(slice(1, 4), fr.Status.MAG_VALID, np.float32(h.mag_scale).astype(float))
        accel = masked(slice(4, 7), fr.Status.ACCEL_VALID, float(np.float32(h.accel_scale)))
        gyro = masked(slice(7, 10), fr.Status.GYRO_VALID, float(np.float32(h.gyro_scale)))
        temp = masked(slice(10, 11), fr.Status.TEMP_VALID, float(np.float32(h.temp_scale)))[:, 0] + h.temp_offset
        return SampleBlock(t=self._unwrap_times(v[:, 0]), mag=mag, accel=accel, gyro=gyro, temp=temp,
                           source=self.source)

    def _unwrap_times(self, t_us: np.ndarray, advance: bool = True) -> np.ndarray:
        """Board µs (uint32, wraps every 71.6 min) → seconds, continuing across blocks."""
        if len(t_us) == 0:
            return np.zeros(0)
        prev = self._t_last if self._t_last is not None else int(t_us[0])
        steps = np.diff(np.concatenate([[prev], t_us]))
        wraps = self._t_wrap + np.cumsum(steps < -(1 << 31)) * (1 << 32)
        if advance:
            self._t_last, self._t_wrap = int(t_us[-1]), int(wraps[-1])
        return (t_us + wraps) / 1e6

    def _raw_block(self, items) -> SampleBlock:
        t = np.array([it[0] for it in items], dtype=float)
        accel, gyro, mag = raw_to_si(np.array([it[1] for it in items]))
        return SampleBlock(t=t, mag=mag, accel=accel, gyro=gyro, temp=np.full(len(t), np.nan),
                           source=self.source)

    # -- commands -----------------------------------------------------------------------------
    def _frame(self, msg: fr.Message) -> bytes:
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFFFF
        return fr.encode(msg, seq)

    def _command(self, msg: fr.Message, answer: type, *, retries: int = 3, timeout: float = 1.0) -> fr.Frame:
        name = type(msg).__name__
        for attempt in range(retries + 1):
            if attempt:
                self._stats.retries += 1
            seq = self._seq
            self.port.write(self._frame(msg))
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                for i, frame in enumerate(self._answers):
                    m = frame.msg
                    if isinstance(m, (fr.Ack, fr.Nak)) and m.acked_seq == seq and m.acked_type == msg.TYPE:
                        del self._answers[i]
                        if isinstance(m, fr.Nak):
                            self._stats.naks += 1
                            reason = fr.NakReason(m.reason).name if m.reason in fr.NakReason._value2member_map_ \
                                else str(m.reason)
                            raise LinkError(f"{self.source}: board refused {name} (seq {seq}): {reason}")
                        return frame
                    if answer is not fr.Ack and isinstance(m, answer):
                        del self._answers[i]
                        return frame
                self.pump()
        raise LinkError(f"{self.source}: no answer to {name} after {retries + 1} attempts of {timeout:g} s "
                        "(is the streamcal_bridge sketch running at this baud rate?)")

    def send_calibration(self, cal, cal_id: int | None = None, *, retries: int = 3,
                         timeout: float = 1.0) -> int:
        """Store ``cal`` (a mag :class:`~streamcal.calibration.Calibration` in µT with hard/soft
        iron only) in the board's EEPROM; return the 16-bit ``cal_id`` it was stored under.

        Raises :class:`InputError` if the board cannot apply this calibration, :class:`LinkError`
        if it refuses it or does not answer after ``retries`` retries.
        """
        if cal.sensor != "mag" or cal.unit != "uT":
            raise InputError(f"calibration for sensor {cal.sensor!r} in {cal.unit!r}: the board applies "
                             "magnetometer calibrations in uT only")
        if cal.effects:
            raise InputError(f"calibration has effects {sorted(cal.effects)}: the board applies K and b "
                             "only; refit with --model hard_iron,soft_iron")
        K = np.asarray(cal.K, dtype=float)
        if np.any(np.tril(K, -1) != 0) or np.any(np.diag(K) <= 0) or not np.all(np.isfinite(K)) \
                or not np.all(np.isfinite(cal.b)) \
                or np.max(np.abs(np.concatenate([K.ravel(), np.ravel(cal.b)]))) > np.finfo(np.float32).max:
            raise InputError("calibration K must be upper triangular with a positive diagonal, K and b "
                             "finite and within the board's float32 range")
        if cal_id is None:
            cal_id = zlib.crc32(np.concatenate([K.ravel(), cal.b]).astype("<f8").tobytes()) & 0xFFFF
        self._command(fr.SetCalibration.from_kb(K, cal.b, cal_id=cal_id), fr.Ack,
                      retries=retries, timeout=timeout)
        return cal_id

    def query_calibration(self, *, retries: int = 3, timeout: float = 1.0) -> fr.CalReport:
        """The calibration the board holds (``valid`` 0 if none)."""
        return self._command(fr.QueryCal(), fr.CalReport, retries=retries, timeout=timeout).msg

    def clear_calibration(self, **kw) -> None:
        self._command(fr.ClearCal(), fr.Ack, **kw)

    def start(self, outputs: int = int(fr.Output.SAMPLES | fr.Output.CALIBRATED | fr.Output.SPHERE_SUMS),
              period_us: int = 0, sums_every: int = 100, **kw) -> None:
        """(Re)start streaming; ``outputs`` are :class:`~firmware_bridge.frames.Output` bits."""
        for name, value, top in (("outputs", outputs, 0xFF), ("period_us", period_us, 0xFFFFFFFF),
                                 ("sums_every", sums_every, 0xFFFF)):
            if not 0 <= int(value) <= top:
                raise InputError(f"START {name} must be an integer in 0..{top}, got {value}")
        self._command(fr.Start(outputs=int(outputs), period_us=int(period_us),
                               sums_every=int(sums_every)), fr.Ack, **kw)

    def stop(self, **kw) -> None:
        self._command(fr.Stop(), fr.Ack, **kw)

    def request_info(self, *, retries: int = 3, timeout: float = 1.0) -> fr.Hello:
        """Ask for HELLO again (board identity and scales)."""
        before = self.hello
        for attempt in range(retries + 1):
            if attempt:
                self._stats.retries += 1
            self.hello = None
            self.port.write(self._frame(fr.GetInfo()))
            deadline = time.monotonic() + timeout
            while self.hello is None and time.monotonic() < deadline:
                self.pump()
            if self.hello is not None:
                return self.hello
        self.hello = before
        raise LinkError(f"{self.source}: no HELLO after {retries + 1} requests")
