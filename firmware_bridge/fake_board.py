"""A simulated Arduino running ``arduino/streamcal_bridge`` that replays a track over a pty.

The board lives on the master side of ``os.openpty()`` in a thread; the host opens
:attr:`FakeBoard.port_name` (the slave) like a real ``/dev/ttyACM0``. It behaves as the sketch
does: it turns the track's SI samples into the raw int16 counts the sketch would read (same
scales, AK8963 16-bit range and overflow), numbers every frame it sends, answers commands, keeps
a calibration in a simulated EEPROM with the sketch's layout, streams the calibrated directions
``K⁻¹(m − b)`` computed in float32, and the 25 sphere sums (same integer algorithm).

Like a Uno that resets when its port is opened, the board stays in reset until the host sends
its first byte, so a host sees every frame from the boot HELLO on. Optional faults (dropped,
corrupted, truncated frames, garbage between frames) exercise the host's accounting.

    with FakeBoard.from_track(Track.read("track.csv")) as board:
        port = serial.Serial(board.port_name, 115200, timeout=0.05)
"""
from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass

import numpy as np

from streamcal.constants import GRAVITY
from streamcal.errors import InputError

from . import frames as fr
from . import registers as R
from .fake_encoding import ak8963_layout

# Scales the sketch announces (streamcal_bridge.ino; PS-MPU-9250A-01 p8/p9/p12), as float32.
ACCEL_SCALE = float(np.float32(GRAVITY) / np.float32(8192.0))      # m/s² per count (±4 g)
GYRO_SCALE = float(np.float32(3.14159265) / np.float32(180.0) / np.float32(16.4))  # rad/s per count
TEMP_SCALE = float(np.float32(1.0) / np.float32(333.87))          # °C per count
TEMP_OFFSET = 21.0
# 16-bit output, 4912 µT / 32760 counts (HARDWARE.md §4, [RM p50]) in float32, as the sketch's
# AK_UT_PER_LSB (4912.0f / 32760.0f); equals registers.mag_scale(16) to float32 precision.
AK_UT_PER_LSB = float(np.float32(R.MAG_FULL_SCALE_UT) / np.float32(R.MAG_FULL_SCALE_COUNTS[16]))
AK_RANGE = 32760       # |H| beyond this sets ST2.HOFL
SUMS_MAX_N = 1 << 19
SUMS_MAX_D = 2047
EEPROM_SIZE = 1024     # ATmega328P
EE_MAGIC, EE_CAL_ADDR = b"SC\x01", 3
_OUT_HIGH_WATER = 2048  # bytes queued before the board waits (Serial.write blocking)


def mag_scale_from_asa(asa=(128, 128, 128)) -> tuple[float, float, float]:
    """µT per count along body x, y, z from the AK8963 fuse-ROM ASA bytes (x, y, z of the chip),
    as the sketch computes it in float32: body x = chip Hy, y = Hx, z = −Hz."""
    s = [np.float32(AK_UT_PER_LSB) * np.float32(a + 128) / np.float32(256.0) for a in asa]
    return float(s[1]), float(s[0]), float(s[2])


def sphere_sums_add(sums: fr.SphereSums, mag_counts: np.ndarray) -> fr.SphereSums:
    """Add (n,3) mag counts to the running sums exactly as ``sc_sums_add`` does on the board
    (first sample after a reset is the center; ``|d| > 2047`` or a full ``n`` is rejected)."""
    m = np.asarray(mag_counts, dtype=np.int64).reshape(-1, 3)
    if len(m) == 0:
        return sums
    center = np.array(sums.center, dtype=np.int64)
    if sums.n == 0 and sums.rejected == 0:
        center = m[0].copy()
    d = m - center
    in_range = np.all(np.abs(d) <= SUMS_MAX_D, axis=1)
    accepted = in_range & (np.cumsum(in_range) <= SUMS_MAX_N - sums.n)
    d = d[accepted]
    q = d * d
    pj, pk = np.array(fr.SUM_PAIRS).T
    s3 = (q[:, :, None] * d[:, None, :]).sum(axis=0).reshape(9)
    add = lambda old, new: tuple(int(a) + int(b) for a, b in zip(old, new))  # noqa: E731
    return fr.SphereSums(n=sums.n + int(accepted.sum()), rejected=sums.rejected + int((~accepted).sum()),
                         center=tuple(int(c) for c in center), s1=add(sums.s1, d.sum(axis=0)),
                         s2=add(sums.s2, (d[:, pj] * d[:, pk]).sum(axis=0)), s3=add(sums.s3, s3),
                         s4=add(sums.s4, (q[:, pj] * q[:, pk]).sum(axis=0)))


def apply_calibration_f32(cal: fr.SetCalibration, mag_uT: np.ndarray) -> np.ndarray:
    """(n,3) µT → (n,3) ``x = K⁻¹(m − b)`` by back substitution in float32, as ``sc_cal_apply``."""
    f = np.float32
    k, b = np.array(cal.k, dtype=f), np.array(cal.b, dtype=f)
    d = np.asarray(mag_uT, dtype=f) - b
    x2 = d[:, 2] / k[5]
    x1 = (d[:, 1] - k[4] * x2) / k[3]
    x0 = (d[:, 0] - k[1] * x1 - k[2] * x2) / k[0]
    return np.stack([x0, x1, x2], axis=1)


@dataclass(frozen=True)
class Faults:
    """Per-frame probabilities of line faults injected by the fake board (seeded, repeatable);
    the boot HELLO (sequence 0) is always sent intact."""

    drop: float = 0.0       # the frame never leaves (its sequence number is used up)
    corrupt: float = 0.0    # one bit of header/body/CRC flipped before COBS
    truncate: float = 0.0   # the frame loses its tail but keeps its delimiter
    garbage: float = 0.0    # random bytes (with a delimiter) inserted before the frame
    seed: int = 0


class FakeBoard:
    """The sketch, simulated, replaying samples on a pseudo-terminal.

    Arrays (N rows, NaN where a sensor was not sampled): ``t`` (N,) s, ``mag`` (N,3) µT body axes,
    ``accel`` (N,3) m/s², ``gyro`` (N,3) rad/s, ``temp`` (N,) °C. ``speed`` None replays as fast
    as the host reads, 1.0 in real time. ``eeprom`` (1024 bytes) carries a calibration across a
    simulated reboot.
    """

    def __init__(self, t, mag, accel=None, gyro=None, temp=None, *, asa=(128, 128, 128),
                 eeprom: bytes | None = None, speed: float | None = None,
                 faults: Faults | None = None, whoami: int = 0x71):
        t = np.asarray(t, dtype=float)
        n = len(t)
        nan3 = np.full((n, 3), np.nan)
        self.mag_scale = mag_scale_from_asa(asa)
        self.t_us = (np.round((t - (t[0] if n else 0.0)) * 1e6).astype(np.int64) & 0xFFFFFFFF)
        mag = np.asarray(mag, dtype=float) if mag is not None else nan3
        accel = np.asarray(accel, dtype=float) if accel is not None else nan3
        gyro = np.asarray(gyro, dtype=float) if gyro is not None else nan3
        temp = np.asarray(temp, dtype=float) if temp is not None else np.full(n, np.nan)
        self._encode_counts(mag, accel, gyro, temp)
        dt = np.diff(t)
        self.period_us = int(round(np.median(dt) * 1e6)) if len(dt) and np.median(dt) > 0 else 10000
        self.whoami = whoami
        self.speed = speed
        self.faults = faults or Faults()
        self._rng = np.random.default_rng(self.faults.seed)
        self.eeprom = bytearray(eeprom) if eeprom is not None else bytearray(b"\xff" * EEPROM_SIZE)
        self.seq = 0
        self.index = 0
        self.commands: list[fr.Frame] = []
        self.finished = threading.Event()
        self._decoder = fr.FrameDecoder()
        self._out = bytearray()
        self._booted = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port_name = os.ttyname(self._slave)
        self._load_calibration()

    @classmethod
    def from_track(cls, track, **options) -> "FakeBoard":
        """A board replaying a recording (``t``, ``columns``, ``metadata``: a Track).

        The magnetometer is a µT track, or a raw-counts MPU-9250/AK8963 log served as the sketch
        reads such a chip: its counts (chip axes remapped to body axes, 14-bit ×4 to the 16-bit
        output) sent unchanged, with the log's fuse-ROM ASA bytes (the metadata rules of
        :meth:`~.fake_mpu9250.FakeMPU9250Bus.from_track`, so ``fake:`` boards and buses accept
        the same logs).

        Raises:
            InputError: a magnetometer unit other than µT, or counts whose metadata do not say
                they are MPU-9250/AK8963 counts (the message names the file).
        """
        cols = track.columns
        nan = np.full(len(track), np.nan)
        triple = lambda names: np.stack([cols.get(c, nan) for c in names], axis=1)  # noqa: E731
        mag = triple(("mx", "my", "mz"))
        unit = getattr(track, "mag_unit", "uT")
        if unit == "counts":
            counts, asa = _ak8963_counts(track, mag)
            options.setdefault("asa", asa)
            mag = counts * np.array(mag_scale_from_asa(options["asa"]))   # rounds back to counts
        elif unit not in ("uT", "µT"):
            where = getattr(track, "path", None) or "track"
            raise InputError(f"{where}: mag_unit {unit!r}: the fake board replays µT tracks, or "
                             "raw AK8963 counts of an MPU-9250 log (# mag_unit: counts with "
                             "# sensor: mpu9250 … and # mag_axes: AK8963 chip axes)")
        return cls(track.t, mag, triple(("ax", "ay", "az")),
                   triple(("gx", "gy", "gz")), cols.get("temp"), **options)

    # -- counts as the sketch reads them ------------------------------------------------------
    def _encode_counts(self, mag, accel, gyro, temp):
        def counts(values, scale, limit):
            c = np.round(np.nan_to_num(values / scale))
            return np.clip(c, -limit - 1, limit).astype(np.int64)

        status = np.zeros(len(mag), dtype=np.int64)
        mag_counts = counts(mag, np.array(self.mag_scale), 32767)
        has_mag = np.all(np.isfinite(mag), axis=1)
        overflow = has_mag & np.any(np.abs(mag_counts) > AK_RANGE, axis=1)
        mag_counts[~has_mag | overflow] = 0
        status |= np.where(has_mag & ~overflow, int(fr.Status.MAG_VALID), 0)
        status |= np.where(overflow, int(fr.Status.MAG_OVERFLOW), 0)
        status |= np.where(np.all(np.isfinite(accel), axis=1), int(fr.Status.ACCEL_VALID), 0)
        status |= np.where(np.all(np.isfinite(gyro), axis=1), int(fr.Status.GYRO_VALID), 0)
        status |= np.where(np.isfinite(temp), int(fr.Status.TEMP_VALID), 0)
        self.mag_counts = mag_counts
        self.accel_counts = counts(accel, ACCEL_SCALE, 32767)
        self.gyro_counts = counts(gyro, GYRO_SCALE, 32767)
        self.temp_counts = counts(temp - TEMP_OFFSET, TEMP_SCALE, 32767)
        self.status = status
        self.mag_uT = (self.mag_counts.astype(np.float32) * np.array(self.mag_scale, dtype=np.float32))

    # -- calibration and EEPROM ---------------------------------------------------------------
    def _load_calibration(self):
        self.calibration: fr.SetCalibration | None = None
        if bytes(self.eeprom[:3]) != EE_MAGIC:
            return
        block = bytes(self.eeprom[EE_CAL_ADDR:EE_CAL_ADDR + fr.SetCalibration.body_size()])
        cal = fr.SetCalibration.unpack_body(block)
        if _cal_reason(cal) == 0:
            self.calibration = cal

    def _store_calibration(self, cal: fr.SetCalibration):
        block = cal.pack_body()
        self.eeprom[0] = 0xFF
        self.eeprom[EE_CAL_ADDR:EE_CAL_ADDR + len(block)] = block
        self.eeprom[0:3] = EE_MAGIC

    @property
    def sums(self) -> fr.SphereSums:
        """The board's sphere sums up to the last sample sent."""
        self._catch_up_sums()
        return self._sums

    # -- life cycle -----------------------------------------------------------------------------
    def start(self) -> "FakeBoard":
        self._thread = threading.Thread(target=self._run, name="fake-board", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self.start() if self._thread is None else self

    def __exit__(self, *exc):
        self.close()

    @property
    def frames_sent(self) -> int:
        """Frames the board has numbered so far (the next sequence number, unwrapped)."""
        return self.seq

    # -- the sketch's loop --------------------------------------------------------------------
    def _boot(self):
        self._booted = True
        self.streaming = True
        self.outputs = int(fr.Output.SAMPLES | fr.Output.CALIBRATED | fr.Output.SPHERE_SUMS)
        self.sums_every = 100
        self._sums = fr.SphereSums()
        self._sums_from = self.index
        self._sums_since = 0
        self._t0 = time.monotonic()
        self._send(self._hello())

    def _run(self):
        while not self._stop.is_set():
            ready = self._booted and self.streaming and self.index < len(self.t_us) \
                and len(self._out) < _OUT_HIGH_WATER and self._due()
            wait = 0 if ready else 0.01
            try:
                readable, writable, _ = select.select([self._master], [self._master] if self._out else [],
                                                      [], wait)
            except (OSError, ValueError):
                return
            if readable:
                self._receive()
            if writable or self._out:
                self._flush()
            if ready:
                self._emit_sample()
            elif self._booted and self.index >= len(self.t_us) and not self._out:
                self.finished.set()  # only once the last frame has left: a host may stop reading then

    def _due(self) -> bool:
        if self.speed is None:
            return True
        return time.monotonic() - self._t0 >= self.t_us[self.index] / 1e6 / self.speed

    def _receive(self):
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # host side not open (EIO): nothing to read
        if data and not self._booted:
            self._boot()  # the host opened the port: DTR resets a Uno
        for frame in self._decoder.feed(data):
            self.commands.append(frame)
            self._handle(frame)

    def _flush(self):
        try:
            n = os.write(self._master, self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._out.clear()
            return
        del self._out[:n]

    def _send(self, msg: fr.Message):
        seq = self.seq
        self.seq += 1
        f, rng = self.faults, self._rng
        if seq == 0:  # the boot HELLO always arrives: it anchors the host's loss count in tests
            self._out += fr.encode(msg, seq)
            return
        if f.garbage and rng.random() < f.garbage:
            self._out += bytes(rng.integers(1, 256, size=int(rng.integers(1, 40)), dtype=np.uint8)) + b"\x00"
        if f.drop and rng.random() < f.drop:
            return
        payload = bytearray(fr.encode_payload(msg, seq))
        if f.corrupt and rng.random() < f.corrupt:
            bit = int(rng.integers(len(payload) * 8))
            payload[bit // 8] ^= 1 << (bit % 8)
        wire = fr.cobs.encode(bytes(payload))
        if f.truncate and rng.random() < f.truncate:
            wire = wire[:int(rng.integers(0, len(wire)))]
        self._out += wire + fr.DELIMITER

    def _hello(self) -> fr.Hello:
        flags = (fr.HelloFlags.CAL_LOADED if self.calibration else 0) | fr.HelloFlags.MAG_PRESENT \
            | (fr.HelloFlags.STREAMING if self.streaming else 0)
        return fr.Hello(fw_major=1, fw_minor=0, whoami=self.whoami, ak_wia=0x48, flags=int(flags),
                        period_us=self.period_us, accel_scale=ACCEL_SCALE, gyro_scale=GYRO_SCALE,
                        temp_scale=TEMP_SCALE, temp_offset=TEMP_OFFSET, mag_scale=self.mag_scale)

    def _emit_sample(self):
        i = self.index
        self.index += 1
        status = int(self.status[i]) | (int(fr.Status.CAL_ACTIVE) if self.calibration else 0)
        if self.outputs & fr.Output.SAMPLES:
            self._send(fr.Sample(t_us=int(self.t_us[i]), mag=tuple(int(v) for v in self.mag_counts[i]),
                                 accel=tuple(int(v) for v in self.accel_counts[i]),
                                 gyro=tuple(int(v) for v in self.gyro_counts[i]),
                                 temp=int(self.temp_counts[i]), status=status))
        if not status & fr.Status.MAG_VALID:
            return
        if self.calibration and self.outputs & fr.Output.CALIBRATED:
            x = apply_calibration_f32(self.calibration, self.mag_uT[i:i + 1])[0]
            self._send(fr.CalSample(t_us=int(self.t_us[i]), x=tuple(float(v) for v in x), status=status))
        self._sums_since += 1
        if self.outputs & fr.Output.SPHERE_SUMS and self.sums_every and self._sums_since >= self.sums_every:
            self._sums_since = 0
            self._send(self.sums)

    def _catch_up_sums(self):
        rows = np.arange(self._sums_from, self.index)
        valid = rows[(self.status[rows] & int(fr.Status.MAG_VALID)) != 0]
        self._sums = sphere_sums_add(self._sums, self.mag_counts[valid])
        self._sums_from = self.index

    def _ack(self, frame: fr.Frame, reason: int = 0):
        if reason:
            self._send(fr.Nak(acked_type=int(frame.type), acked_seq=frame.seq, reason=reason))
        else:
            self._send(fr.Ack(acked_type=int(frame.type), acked_seq=frame.seq))

    def _handle(self, frame: fr.Frame):
        msg = frame.msg
        if isinstance(msg, fr.GetInfo):
            self._send(self._hello())
        elif isinstance(msg, fr.QueryCal):
            cal = self.calibration or fr.SetCalibration(k=(0.0,) * 6, b=(0.0,) * 3)
            self._send(fr.CalReport(valid=1 if self.calibration else 0, cal_id=cal.cal_id, k=cal.k,
                                    b=cal.b, crc=cal.crc))
        elif isinstance(msg, fr.Stop):
            self.streaming = False
            self._ack(frame)
        elif isinstance(msg, fr.ClearCal):
            self.eeprom[0] = 0xFF
            self.calibration = None
            self._ack(frame)
        elif isinstance(msg, fr.Start):
            self.outputs = msg.outputs
            if msg.period_us >= 2000:
                self.period_us = msg.period_us
            self.sums_every = msg.sums_every
            if msg.outputs & fr.Output.RESET_SUMS:
                self._sums, self._sums_from, self._sums_since = fr.SphereSums(), self.index, 0
            self.streaming = True
            self._ack(frame)
        elif isinstance(msg, fr.SetCalibration):
            reason = _cal_reason(msg)
            if reason == 0:
                self._store_calibration(msg)
                self.calibration = msg
            self._ack(frame, reason)
        else:
            self._ack(frame, fr.NakReason.UNKNOWN_TYPE)


def _ak8963_counts(track, mag):
    """(N,3) body-axis 16-bit counts and the ASA bytes of a raw-counts track's magnetometer
    ``mag`` (N,3), by the track's AK8963 metadata (InputError when it has none)."""
    where = str(getattr(track, "path", None) or "track")
    layout = ak8963_layout(dict(getattr(track, "metadata", None) or {}), where)
    counts = mag if layout.body_axes else mag @ R.AK_TO_BODY.T
    if layout.bits == 14:
        counts = 4.0 * counts
    return counts, layout.asa


def _cal_reason(cal: fr.SetCalibration) -> int:
    """0 if the board accepts the block, else the NAK reason (mirror of ``sc_cal_check``)."""
    if not cal.crc_ok():
        return fr.NakReason.BAD_CAL_CRC
    if not all(math.isfinite(v) for v in cal.k + cal.b):
        return fr.NakReason.BAD_CAL_VALUES
    if not (cal.k[0] > 0 and cal.k[3] > 0 and cal.k[5] > 0):
        return fr.NakReason.BAD_CAL_VALUES
    return 0
