"""A register-level fake MPU-9250 + AK8963 behind an smbus2-compatible bus, replaying a track.

The fake converts the track back to what the chips would hold — raw int16 counts under the
full-scale ranges currently written to the registers, the AK8963 axes (inverse of the fixed
remap), the inverse of the fuse-ROM sensitivity adjustment, big-endian accel/gyro/temp and
little-endian magnetometer bytes — so a driver reading it exercises its real decoding path.

It honours the register protocol the driver must follow: H_RESET restores defaults, the AK8963
at 0x0C answers only with INT_PIN_CFG.BYPASS_EN set (and I2C_MST_EN clear), DRDY appears only
in a continuous mode, the fuse ROM reads back only in fuse-ROM mode, AK8963 mode changes must
pass through power-down, and the data read ends with ST2. Departures are recorded in
:attr:`FakeMPU9250Bus.violations` rather than raised, as a real chip would not complain either.

Time: with ``clock`` (a callable returning seconds), track time follows it from construction.
Without it, each read of ST1 advances to the next magnetometer sample (each burst read of the
accelerometer when the chip has no magnetometer), and every refused transaction while the device
is absent advances by one magnetometer period, so tests are deterministic and never sleep.

Replaying raw AK8963 logs: a track in ``mag_unit: counts`` whose metadata says it comes from an
MPU-9250/AK8963 (``# sensor: mpu9250 …`` or ``ak8963``, plus ``# mag_axes: AK8963 chip axes`` or
``… body axes``) holds what the data registers held. :meth:`FakeMPU9250Bus.from_track` serves
those counts into HXL..HZH unchanged (chip axes; a body-axis log is turned back with the fixed
remap, a 14-bit log is scaled ×4 to the driver's 16-bit output, exactly), with fuse-ROM ASA bytes
128 (adjustment 1.0) unless ``# asa: 176,178,165`` states them, so the driver applies its own
remap, ASA and 4912/32760 µT/LSB scale and yields µT in body axes. A counts track without that
metadata, or in counts of another sensor, is an :class:`~streamcal.errors.InputError` saying why.

A log without accelerometer, gyro or temperature columns is served as the board at rest: accel
(0, 0, +9.80665) m/s², gyro 0 rad/s, temperature 25 °C at every row time; ``from_track`` logs a
warning and lists the substitution in :attr:`FakeMPU9250Bus.notes`. Timing always comes from ``t``.

The parts: the two dies' register logic (:mod:`.fake_mpu_die`, :mod:`.fake_ak8963`), the replay
encoding track → counts (:mod:`.fake_encoding`), and here the bus that routes each transaction
by address to a die, keeps the track time and injects the faults.

Faults (seeded, :class:`Faults`): NACK rate, HOFL overflow samples, DOR overruns (skipped
samples), wrong WHO_AM_I (``who_am_i=``), the device vanishing for a time window and returning
at power-on defaults, and spontaneous resets.

Example::

    bus = FakeMPU9250Bus(t, mag=m_uT, accel=a, gyro=w, temp=T, faults=Faults(nack_rate=0.05))
    drv = MPU9250(bus, clock=bus.now)
    bus = FakeMPU9250Bus.from_track(Track.read("tiva_mpu9250_mag_02.csv"))   # raw AK8963 counts, no IMU
"""
from __future__ import annotations

import ctypes
import errno as errno_mod
import logging
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from streamcal.errors import InputError

from . import registers as R
from .fake_ak8963 import Ak8963Die
from .fake_ak8963 import wrap as ak_wrap
from .fake_encoding import AT_REST, AkLayout, EncodedRows, Replay, replay_arguments  # noqa: F401
from .fake_mpu_die import MpuDie

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Faults:
    """Fault injection for :class:`FakeMPU9250Bus`.

    Attributes:
        nack_rate: probability that any transaction fails before reaching the chip.
        nack_errnos: errno values drawn for those failures (121 EREMOTEIO, 5 EIO, 110 ETIMEDOUT…).
        hofl_rate: probability that a magnetometer sample carries ST2.HOFL.
        dor_rate: probability that a magnetometer sample is skipped (step mode; in clock mode
            skips come from polling too slowly).
        vanish: ``(t_start, t_end)`` track-time windows in which nothing answers; the chips
            return at power-on defaults.
        self_resets: ``(t, which)`` spontaneous resets, ``which`` in ``"mpu"``, ``"ak"``, ``"both"``.
    """

    nack_rate: float = 0.0
    nack_errnos: Sequence[int] = (errno_mod.EREMOTEIO,)
    hofl_rate: float = 0.0
    dor_rate: float = 0.0
    vanish: Sequence[tuple[float, float]] = ()
    self_resets: Sequence[tuple[float, str]] = ()


@dataclass
class _Counters:
    transactions: int = 0
    nacks: int = 0
    refused_absent: int = 0
    hofl: int = 0
    dor_reported: int = 0
    skipped: int = 0
    resets: int = 0
    samples_latched: int = 0


class FakeMPU9250Bus:
    """In-memory smbus2 look-alike holding one MPU-9250 and its AK8963, replaying a track.

    Args:
        t: (N,) seconds, non-decreasing.
        mag: (N,3) µT in body (accelerometer) axes, NaN rows where not sampled.
        mag_counts: instead of ``mag``: (N,3) raw AK8963 counts in chip axes as the data
            registers held them (ASA not applied), NaN rows where not sampled; served unchanged
            at ``mag_counts_bits`` output and rescaled exactly for the other output width.
        mag_counts_bits: output width (16 or 14) the ``mag_counts`` were recorded at.
        accel: (N,3) m/s²; gyro: (N,3) rad/s; temp: (N,) °C (NaN where not sampled).
        address: 0x68 (AD0 low) or 0x69 (AD0 high).
        who_am_i: value of WHO_AM_I (0x71 MPU-9250, 0x73 MPU-9255, 0x70 MPU-6500…).
        magnetometer: whether an AK8963 is present; default from the WHO_AM_I table.
        ak_wia: AK8963 WIA value; asa: fuse-ROM ASAX/ASAY/ASAZ bytes.
        power_on_pwr_mgmt_1: PWR_MGMT_1 after reset/power-on; 0x01 per [RM p9], 0x41 to model a
            part that wakes up asleep (SLEEP set: data registers read 0).
        clock: seconds callable; None → step mode (see module docstring).
        faults: :class:`Faults`; seed: RNG seed for them.
    """

    def __init__(self, t, mag=None, accel=None, gyro=None, temp=None, *,
                 address: int = R.MPU_ADDRESS_AD0_LOW, who_am_i: int = 0x71,
                 magnetometer: bool | None = None, ak_wia: int = R.AK8963_WIA,
                 asa: Sequence[int] = (0xB0, 0xB2, 0xA5), clock: Callable[[], float] | None = None,
                 faults: Faults = Faults(), seed: int = 0,
                 power_on_pwr_mgmt_1: int = R.MPU_RESET_VALUES[R.MpuReg.PWR_MGMT_1],
                 mag_counts=None, mag_counts_bits: int = 16):
        if address not in R.MPU_ADDRESSES:
            raise ValueError(f"address must be 0x68 or 0x69, got 0x{address:02X}")
        self.t = np.asarray(t, dtype=float).reshape(-1)
        if self.t.size == 0:
            raise ValueError("the track to replay is empty")
        self.address, self.who_am_i, self.ak_wia = address, who_am_i, ak_wia
        self.power_on_pwr_mgmt_1 = power_on_pwr_mgmt_1
        chip = R.WHO_AM_I_TABLE.get(who_am_i)
        self.has_mag = (chip.has_magnetometer if chip else False) if magnetometer is None \
            else bool(magnetometer)
        self.asa = np.asarray(asa, dtype=np.uint8)
        self.faults, self.rng = faults, np.random.default_rng(seed)
        self.replay = Replay(self.t, mag, accel, gyro, temp, asa=self.asa, mag_counts=mag_counts,
                             mag_counts_bits=mag_counts_bits)
        mag_t = self.replay.mag_t
        self.replay.hofl_fault = self.rng.random(len(mag_t)) < faults.hofl_rate
        self.imu_clock_t = self.replay.acc_t if self.replay.acc_t.size else self.replay.gyr_t
        dt = np.diff(mag_t if mag_t.size > 1 else self.imu_clock_t)
        self.step_dt = float(np.median(dt)) if dt.size else 0.01
        self._clock = clock
        self._clock0 = clock() if clock is not None else 0.0
        self._tau = self.t[0] - self.step_dt      # step-mode track time
        self._events = sorted((float(ts), w) for ts, w in faults.self_resets)
        self._vanish = [(float(a), float(b)) for a, b in faults.vanish]
        self._absent = False
        self._imu_next = 0
        self.counters = _Counters()
        self.hofl_indices: list[int] = []   # magnetometer-row indices served with HOFL
        self.violations: list[str] = []
        self.notes: list[str] = []           # how the track was interpreted (from_track)
        self.closed = False
        self.mpu = MpuDie(self)
        self.ak = Ak8963Die(self)

    # --- construction from a recording ---------------------------------------------------------
    @classmethod
    def from_track(cls, track, **kwargs) -> "FakeMPU9250Bus":
        """Replay a ``streamcal.inputs.track.Track`` (anything with ``t``, ``columns`` and ``metadata``).

        A µT track is encoded back to counts; a raw AK8963 counts log is served unchanged (see
        the module docstring); missing accel/gyro/temp are served as the board at rest.

        Raises:
            InputError: naming the file (or "track") and what the fake cannot replay: a unit
                other than µT, counts without MPU-9250/AK8963 metadata, an accelerometer unit
                other than m/s², an empty track.
        """
        path = getattr(track, "path", None)
        where = str(path) if path is not None else "track"
        channels, notes, at_rest, asa = replay_arguments(track, where)
        if asa is not None:
            kwargs.setdefault("asa", asa)
        try:
            bus = cls(track.t, **channels, **kwargs)
        except ValueError as e:
            raise InputError(f"{where}: cannot replay on the fake bus: {e}") from e
        bus.notes = notes
        for note in notes:
            (log.warning if note is at_rest else log.info)("fake bus replaying %s: %s", where, note)
        return bus

    # --- time ----------------------------------------------------------------------------------
    def now(self) -> float:
        """Current track time, s (usable as the driver's clock)."""
        if self._clock is not None:
            return float(self.t[0] + (self._clock() - self._clock0))
        return float(self._tau)

    @property
    def finished(self) -> bool:
        """True once every sample of the track has been served (or its time has passed)."""
        if self._clock is not None:
            return self.now() > self.t[-1]
        if self.has_mag:
            return self.replay.mag_t.size == 0 or self._tau >= self.replay.mag_t[-1]
        return self._imu_next >= len(self.imu_clock_t)

    @property
    def clocked(self) -> bool:
        """True when track time follows ``clock``; False in step mode."""
        return self._clock is not None

    def advance_to(self, tau: float) -> None:
        """Step mode: move the track time to ``tau`` (s) and apply what happened by then."""
        self._tau = tau
        self._sync()

    def imu_step(self) -> None:
        """Step mode without a magnetometer: a data read advances to the next IMU row."""
        if self._clock is None and not self.has_mag and self._imu_next < len(self.imu_clock_t):
            self._tau = self.imu_clock_t[self._imu_next]
            self._imu_next += 1

    def _sync(self) -> float:
        tau = self.now()
        while self._events and self._events[0][0] <= tau:
            _, which = self._events.pop(0)
            self.counters.resets += 1
            if which in ("mpu", "both"):
                self.mpu.power_on()
            if which in ("ak", "both"):
                self.ak.power_on()
        inside = any(a <= tau < b for a, b in self._vanish)
        if self._absent and not inside:
            self._absent = False
            self.mpu.power_on()
            self.ak.power_on()
        self._absent = inside
        if self.has_mag and self.ak.continuous() and self._clock is not None:
            self.ak.latch_until(tau)
        return tau

    # --- bus plumbing ----------------------------------------------------------------------------
    def _begin(self, address: int) -> None:
        if self.closed:
            raise ValueError("I/O operation on closed bus")
        self.counters.transactions += 1
        if self.faults.nack_rate and self.rng.random() < self.faults.nack_rate:
            self.counters.nacks += 1
            e = int(self.rng.choice(np.asarray(self.faults.nack_errnos)))
            raise OSError(e, f"[Errno {e}] injected fault at 0x{address:02X}")
        self._sync()
        if not self._present(address):
            if self._absent and self._clock is None:
                self._tau += self.step_dt
            self.counters.refused_absent += 1
            raise OSError(errno_mod.EREMOTEIO, "Remote I/O error")

    def _present(self, address: int) -> bool:
        if self._absent:
            return False
        if address == self.address:
            return True
        if address == R.AK8963_ADDRESS and self.has_mag:
            return bool(self.mpu.field(R.MpuReg.INT_PIN_CFG, R.BYPASS_EN)
                        and not self.mpu.field(R.MpuReg.USER_CTRL, R.I2C_MST_EN))
        return False

    def _read(self, address: int, register: int, length: int) -> list[int]:
        if address == R.AK8963_ADDRESS:
            return self.ak.read(register, length)
        return self.mpu.read(register, length)

    def _write(self, address: int, register: int, data: Sequence[int]) -> None:
        for i, value in enumerate(data):
            if address == R.AK8963_ADDRESS:
                self.ak.write(ak_wrap(register, i), int(value) & 0xFF)
            else:
                self.mpu.write((register + i) & 0x7F, int(value) & 0xFF)

    # --- smbus2 method set -----------------------------------------------------------------------
    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        self._begin(i2c_addr)
        return self._read(i2c_addr, register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        self._begin(i2c_addr)
        self._write(i2c_addr, register, [value])

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None):
        if length > R.SMBUS_BLOCK_MAX:   # smbus2 raises before any I/O, and so do we
            raise ValueError(f"Desired block length over {R.SMBUS_BLOCK_MAX} bytes")
        self._begin(i2c_addr)
        return self._read(i2c_addr, register, length)

    def write_i2c_block_data(self, i2c_addr: int, register: int, data, force=None) -> None:
        if len(data) > R.SMBUS_BLOCK_MAX:
            raise ValueError(f"Data length cannot exceed {R.SMBUS_BLOCK_MAX} bytes")
        self._begin(i2c_addr)
        self._write(i2c_addr, register, list(data))

    def i2c_rdwr(self, *i2c_msgs) -> None:
        """Combined transaction of ``smbus2.i2c_msg``: a write sets the register pointer (first
        byte) and writes the rest; a read fills its buffer from the pointer onwards."""
        from smbus2.smbus2 import I2C_M_RD
        if not i2c_msgs:
            return
        self._begin(i2c_msgs[0].addr)
        pointer: dict[int, int] = {}
        for msg in i2c_msgs:
            if not self._present(msg.addr):
                raise OSError(errno_mod.EREMOTEIO, "Remote I/O error")
            if msg.flags & I2C_M_RD:
                data = bytes(self._read(msg.addr, pointer.get(msg.addr, 0), msg.len))
                ctypes.memmove(msg.buf, data, msg.len)
                pointer[msg.addr] = pointer.get(msg.addr, 0) + msg.len
            else:
                payload = bytes(msg)
                if payload:
                    pointer[msg.addr] = payload[0]
                    self._write(msg.addr, payload[0], payload[1:])

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> "FakeMPU9250Bus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- encodings ---------------------------------------------------------------------------------
    def encoded_rows(self, *, accel_fs: int | None = None, gyro_fs: int | None = None,
                     mag_bits: int | None = None) -> EncodedRows:
        """Every row's raw counts as this fake serves them (see :class:`EncodedRows`).

        Settings default to the ones now in ACCEL_CONFIG, GYRO_CONFIG and AK8963 CNTL1.BIT;
        pass them to get another range (e.g. to replay the track on another chip model).
        """
        if accel_fs is None:
            accel_fs = self.mpu.field(R.MpuReg.ACCEL_CONFIG, R.ACCEL_FS_SEL)
        if gyro_fs is None:
            gyro_fs = self.mpu.field(R.MpuReg.GYRO_CONFIG, R.GYRO_FS_SEL)
        if mag_bits is None:
            mag_bits = self.ak.bits()
        return self.replay.encoded_rows(accel_fs, gyro_fs, mag_bits)
