"""MPU-9250 / MPU-9255 (and MPU-6500) driver over an injected smbus2-like bus.

The bus is any object with smbus2's ``read_byte_data``, ``write_byte_data`` and
``read_i2c_block_data`` (plus ``i2c_rdwr`` when ``use_i2c_rdwr=True``): ``smbus2.SMBus(1)`` on a
Raspberry Pi, :class:`firmware_bridge.fake_mpu9250.FakeMPU9250Bus` in tests. Nothing touches
hardware at import time.

What one sample costs on the wire: an 8-byte burst from AK8963 ST1 (ST1, HXL..HZH, ST2 — ST2 last,
as the AK8963 requires) and, when DRDY is set, an 18-byte burst from INT_PIN_CFG through
GYRO_ZOUT_L. The 4 extra bytes in front of the 14 data bytes carry INT_PIN_CFG: a chip that reset
itself since bring-up shows BYPASS_EN cleared in the very transaction that would otherwise deliver
data scaled with the default ranges, so such a sample is never passed on.

Recovery: every I/O error (OSError: 121 EREMOTEIO = NACK, 5 EIO, 110 ETIMEDOUT…) is retried with
bounded exponential backoff and counted by kind in :attr:`MPU9250.stats`. When retries run out,
the driver checks the chip (WHO_AM_I, configuration registers, AK8963 CNTL1): a chip found at its
reset defaults — it browned out, or was unplugged and came back — is initialised again
(``stats["reinits"]``); a chip that does not answer raises :class:`DeviceIOError` naming the
register and address, and the next call starts with the same check.

Example::

    from smbus2 import SMBus
    with SMBus(1) as bus:
        imu = MPU9250(bus)                 # bring-up, WHO_AM_I and AK8963 checks, fuse ROM
        r = imu.read_sample()              # Reading or None (no new magnetometer data yet)
        block = imu.read_block(100)        # SampleBlock: t s, mag µT, accel m/s², gyro rad/s, temp °C
"""
from __future__ import annotations

import errno as errno_mod
import logging
import os
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from streamcal.errors import InputError, StreamcalError

from . import registers as R
from streamcal.samples import SampleBlock

log = logging.getLogger(__name__)

_WIRING_HINT = ("check the I2C address (0x68 with AD0 low, 0x69 with AD0 high), the SDA/SCL wiring, "
                "the pull-up resistors and the 3.3 V supply; `i2cdetect -y 1` lists what answers")
_IMU_BURST_START = R.MpuReg.INT_PIN_CFG       # 4 bytes of status in front of ACCEL_XOUT_H
_IMU_LEAD = R.MpuReg.ACCEL_XOUT_H - _IMU_BURST_START
_NACK_ERRNOS = {errno_mod.EREMOTEIO, errno_mod.ENXIO}
_POLLS_PER_PERIOD = 2.0        # read_block polls at twice the sample rate


class DeviceError(StreamcalError):
    """The sensor on the bus is missing, is the wrong chip, or misbehaves."""

    def __init__(self, message: str, address: int | None = None, register: int | None = None):
        self.address, self.register = address, register
        super().__init__(message)


class WrongDeviceError(DeviceError):
    """WHO_AM_I / WIA names a chip this driver cannot use as asked."""


class DeviceIOError(DeviceError):
    """A bus transfer still failed after every retry."""

    def __init__(self, message: str, address: int, register: int, errno: int | None):
        self.errno = errno
        super().__init__(message, address, register)


@dataclass(frozen=True)
class Reading:
    """One sample. mag (3,) µT in body axes (NaN on an MPU-6500); accel (3,) m/s²;
    gyro (3,) rad/s; temp °C; t seconds on the driver's clock."""

    t: float
    mag: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    temp: float


def decode_imu(raw: np.ndarray, accel_fs: int, gyro_fs: int):
    """(n,14) bytes from ACCEL_XOUT_H → accel (n,3) m/s², temp (n,) °C, gyro (n,3) rad/s."""
    counts = np.ascontiguousarray(raw, dtype=np.uint8).view(R.IMU_DTYPE).astype(float)
    accel = counts[:, 0:3] * R.accel_scale(accel_fs)
    temp = (counts[:, 3] - R.TEMP_ROOM_OFFSET_LSB) / R.TEMP_SENSITIVITY_LSB_PER_C + R.TEMP_ROOM_C
    gyro = counts[:, 4:7] * R.gyro_scale(gyro_fs)
    return accel, temp, gyro


def decode_mag(raw: np.ndarray, asa, bits: int = 16) -> np.ndarray:
    """(n,6) bytes HXL..HZH → (n,3) µT in body axes: scale, fuse-ROM adjustment, axis remap."""
    counts = np.ascontiguousarray(raw, dtype=np.uint8).view(R.MAG_DTYPE).astype(float)
    h_ak = counts * (R.mag_scale(bits) * R.asa_factor(asa))
    return h_ak @ R.AK_TO_BODY.T


class MPU9250:
    """Driver for an MPU-9250 (+AK8963) on an injected bus; see the module docstring.

    Args:
        bus: smbus2-like object.
        address: 0x68 (AD0 low) or 0x69 (AD0 high).
        accel_fs, gyro_fs: full-scale codes 0..3 (±2/4/8/16 g, ±250/500/1000/2000 °/s).
        dlpf: DLPF_CFG / A_DLPFCFG code 1..6 (184…5 Hz); sample_rate_div: SMPLRT_DIV.
        mag_mode: ``AkMode.CONTINUOUS_100HZ`` (default) or ``AkMode.CONTINUOUS_8HZ``.
        require_magnetometer: refuse an MPU-6500 (no AK8963) instead of running without mag.
        retries, backoff_s, backoff_max_s: retry policy for each transfer.
        sleep, clock: injected ``time.sleep`` / ``time.monotonic``.
        use_i2c_rdwr: read with combined ``i2c_rdwr`` transfers instead of SMBus block reads.
        health_every: also check the configuration every this many samples (0 = never).
        init: run :meth:`init` now.
    """

    def __init__(self, bus, address: int = R.MPU_ADDRESS_AD0_LOW, *, accel_fs: int = 1,
                 gyro_fs: int = 1, dlpf: int = 3, sample_rate_div: int = 4,
                 mag_mode: R.AkMode = R.AkMode.CONTINUOUS_100HZ,
                 require_magnetometer: bool = True, retries: int = 5, backoff_s: float = 0.001,
                 backoff_max_s: float = 0.05, sleep: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.monotonic, use_i2c_rdwr: bool = False,
                 health_every: int = 1000, init: bool = True):
        if address not in R.MPU_ADDRESSES:
            raise InputError(f"MPU-9250 address must be 0x68 or 0x69, got 0x{address:02X}")
        if accel_fs not in range(4) or gyro_fs not in range(4):
            raise InputError("accel_fs and gyro_fs are codes 0..3")
        if dlpf not in R.DLPF_BANDWIDTH_HZ:
            raise InputError(f"dlpf must be one of {sorted(R.DLPF_BANDWIDTH_HZ)} (1 kHz path)")
        if mag_mode not in R.AK_CONTINUOUS_RATE_HZ:
            raise InputError("mag_mode must be AkMode.CONTINUOUS_8HZ or AkMode.CONTINUOUS_100HZ")
        if not 0 <= sample_rate_div <= 255:
            raise InputError("sample_rate_div is a byte (0..255)")
        self.bus, self.address = bus, address
        self.accel_fs, self.gyro_fs, self.dlpf = accel_fs, gyro_fs, dlpf
        self.sample_rate_div, self.mag_mode = sample_rate_div, R.AkMode(mag_mode)
        self.require_magnetometer = require_magnetometer
        self.retries, self.backoff_s, self.backoff_max_s = retries, backoff_s, backoff_max_s
        self._sleep, self.clock = sleep, clock
        self.use_i2c_rdwr, self.health_every = use_i2c_rdwr, health_every
        self.chip: R.ChipInfo | None = None
        self.asa: np.ndarray | None = None
        self.stats = dict.fromkeys(
            ("reads", "writes", "retries", "nacks", "io_errors", "timeouts", "other_errors",
             "failures", "samples", "empty_polls", "overflows", "overruns", "reinits",
             "health_checks"), 0)
        self._suspect = False
        self._pending_error: DeviceIOError | None = None
        self._empty_polls = 0
        self._since_health = 0
        self._last_data_t = clock()
        if init:
            self.init()

    # --- configuration as data --------------------------------------------------------------
    @property
    def has_magnetometer(self) -> bool:
        return bool(self.chip and self.chip.has_magnetometer)

    @property
    def mag_rate_hz(self) -> float:
        return R.AK_CONTINUOUS_RATE_HZ[self.mag_mode]

    @property
    def imu_rate_hz(self) -> float:
        return R.output_rate_hz(self.sample_rate_div)

    def _config_bytes(self) -> bytes:
        """Expected SMPLRT_DIV, CONFIG, GYRO_CONFIG, ACCEL_CONFIG, ACCEL_CONFIG2 (0x19..0x1D)."""
        return bytes((self.sample_rate_div, R.DLPF_CFG.set(0, self.dlpf),
                      R.GYRO_FS_SEL.set(0, self.gyro_fs), R.ACCEL_FS_SEL.set(0, self.accel_fs),
                      R.A_DLPFCFG.set(0, self.dlpf)))

    def _int_pin_cfg(self) -> int:
        # Bypass on for every chip (harmless on an MPU-6500): a set bit that a reset clears is
        # what lets each data burst prove the chip kept its configuration.
        return R.BYPASS_EN.set(0, 1)

    def _cntl1(self) -> int:
        return R.AK_BIT_16.set(R.AK_MODE.set(0, self.mag_mode), 1)

    # --- transfers with retry ------------------------------------------------------------------
    def _count_error(self, e: OSError) -> None:
        kind = ("nacks" if e.errno in _NACK_ERRNOS else "io_errors" if e.errno == errno_mod.EIO
                else "timeouts" if e.errno == errno_mod.ETIMEDOUT else "other_errors")
        self.stats[kind] += 1

    def _io(self, what: str, address: int, register: int, fn: Callable, *args):
        delay = self.backoff_s
        for attempt in range(self.retries + 1):
            try:
                return fn(*args)
            except OSError as e:
                self._count_error(e)
                last = e
                if attempt == self.retries:
                    break
                self.stats["retries"] += 1
                self._sleep(delay)
                delay = min(2 * delay, self.backoff_max_s)
        self.stats["failures"] += 1
        reason = os.strerror(last.errno) if last.errno else str(last)
        raise DeviceIOError(
            f"{what} {R.register_name(address, register)} failed {self.retries + 1} times: "
            f"{reason} (errno {last.errno}); {_WIRING_HINT}", address, register, last.errno) from last

    def read_registers(self, address: int, register: int, length: int) -> bytes:
        """``length`` bytes from ``register`` on, in SMBus blocks of at most 32 bytes (or one
        ``i2c_rdwr`` transfer), each retried."""
        if self.use_i2c_rdwr:
            from smbus2 import i2c_msg
            msgs = (i2c_msg.write(address, [register]), i2c_msg.read(address, length))
            self._io("read", address, register, self.bus.i2c_rdwr, *msgs)
            self.stats["reads"] += 1
            return bytes(msgs[1])
        out = bytearray()
        for off in range(0, length, R.SMBUS_BLOCK_MAX):
            n = min(R.SMBUS_BLOCK_MAX, length - off)
            out += bytes(self._io("read", address, register + off, self.bus.read_i2c_block_data,
                                  address, register + off, n))
            self.stats["reads"] += 1
        return bytes(out)

    def _read_byte(self, address: int, register: int) -> int:
        value = self._io("read", address, register, self.bus.read_byte_data, address, register)
        self.stats["reads"] += 1
        return int(value)

    def _write(self, address: int, register: int, value: int) -> None:
        self._io("write", address, register, self.bus.write_byte_data, address, register, value)
        self.stats["writes"] += 1

    # --- bring-up -------------------------------------------------------------------------------
    def identify(self) -> R.ChipInfo:
        """Read WHO_AM_I and say what chip answers; raise with what to check when it is not usable."""
        try:
            who = self._read_byte(self.address, R.MpuReg.WHO_AM_I)
        except DeviceIOError as e:
            raise DeviceIOError(f"no answer from an MPU-9250 at 0x{self.address:02X}: {e}",
                                self.address, R.MpuReg.WHO_AM_I, e.errno) from e
        chip = R.WHO_AM_I_TABLE.get(who)
        where = f"WHO_AM_I (0x75) at 0x{self.address:02X} reads 0x{who:02X}"
        if chip is None:
            raise WrongDeviceError(
                f"{where}, which is not an MPU-9250 (0x71) or MPU-9255 (0x73): another device "
                f"answers at this address, or the bus is unreliable; {_WIRING_HINT}. Many cheap "
                f"'MPU-9250' boards carry an MPU-6500 (0x70) or other part.",
                self.address, R.MpuReg.WHO_AM_I)
        if not chip.supported:
            raise WrongDeviceError(f"{where}: this is an {chip.name}, a different InvenSense part "
                                   f"with other registers; this driver supports the MPU-9250/9255 "
                                   f"(and MPU-6500 without magnetometer)",
                                   self.address, R.MpuReg.WHO_AM_I)
        if not chip.has_magnetometer:
            msg = (f"{where}: this is an {chip.name}, which has NO magnetometer (no AK8963 at "
                   f"0x0C) — the board is sold as an MPU-9250 but cannot measure the magnetic field")
            if self.require_magnetometer:
                raise WrongDeviceError(msg + "; pass require_magnetometer=False to use its "
                                       "accelerometer/gyro only", self.address, R.MpuReg.WHO_AM_I)
            log.warning("%s; running accelerometer/gyro/temperature only", msg)
        return chip

    def init(self) -> None:
        """Full bring-up: identify, reset, clock, ranges, DLPF, rate, bypass, AK8963."""
        self.chip = self.identify()
        a = self.address
        self._write(a, R.MpuReg.PWR_MGMT_1, R.H_RESET.set(0, 1))
        self._sleep(R.RESET_WAIT_S)
        self._write(a, R.MpuReg.PWR_MGMT_1, R.CLKSEL.set(0, R.CLKSEL_AUTO_PLL))
        self._sleep(max(R.GYRO_STARTUP_S, R.ACCEL_STARTUP_S))
        self._write(a, R.MpuReg.PWR_MGMT_2, 0x00)
        for reg, value in zip(range(R.MpuReg.SMPLRT_DIV, R.MpuReg.ACCEL_CONFIG2 + 1),
                              self._config_bytes()):
            self._write(a, reg, value)
        self._write(a, R.MpuReg.USER_CTRL, 0x00)           # I2C master off, so bypass works
        self._write(a, R.MpuReg.INT_PIN_CFG, self._int_pin_cfg())
        self._write(a, R.MpuReg.INT_ENABLE, R.RAW_RDY_EN.set(0, 1))  # INT_STATUS.RAW_DATA_RDY
        got = self.read_registers(a, R.MpuReg.SMPLRT_DIV, 5)
        if got != self._config_bytes():
            raise DeviceError(f"configuration did not stick at 0x{a:02X}: SMPLRT_DIV..ACCEL_CONFIG2 "
                              f"(0x19..0x1D) read {got.hex()} after writing "
                              f"{self._config_bytes().hex()}; {_WIRING_HINT}", a, R.MpuReg.SMPLRT_DIV)
        if self.has_magnetometer:
            self._init_mag()
        self._suspect, self._empty_polls, self._since_health = False, 0, 0
        self._last_data_t = self.clock()

    def _init_mag(self) -> None:
        ak = R.AK8963_ADDRESS
        try:
            wia = self._read_byte(ak, R.AkReg.WIA)
        except DeviceIOError as e:
            raise DeviceIOError(
                f"the AK8963 magnetometer does not answer at 0x0C although INT_PIN_CFG.BYPASS_EN is "
                f"set on the {self.chip.name} at 0x{self.address:02X}; the magnetometer die may be "
                f"damaged, or the part is not a genuine MPU-9250 ({e})", ak, R.AkReg.WIA, e.errno) from e
        if wia != R.AK8963_WIA:
            raise WrongDeviceError(f"WIA (0x00) at 0x0C reads 0x{wia:02X}, expected 0x48 (AK8963); "
                                   f"another device sits at 0x0C or the bus is unreliable", ak, R.AkReg.WIA)
        self._write(ak, R.AkReg.CNTL1, R.AkMode.POWER_DOWN)
        self._sleep(R.AK_MODE_WAIT_S)
        self._write(ak, R.AkReg.CNTL1, R.AkMode.FUSE_ROM)
        self._sleep(R.AK_MODE_WAIT_S)
        self.asa = np.frombuffer(self.read_registers(ak, R.AkReg.ASAX, 3), dtype=np.uint8).copy()
        self._write(ak, R.AkReg.CNTL1, R.AkMode.POWER_DOWN)
        self._sleep(R.AK_MODE_WAIT_S)
        self._write(ak, R.AkReg.CNTL1, self._cntl1())
        self._sleep(R.AK_MODE_WAIT_S)
        cntl1 = self._read_byte(ak, R.AkReg.CNTL1)
        if cntl1 != self._cntl1():
            raise DeviceError(f"CNTL1 (0x0A) at 0x0C reads 0x{cntl1:02X} after writing "
                              f"0x{self._cntl1():02X}", ak, R.AkReg.CNTL1)

    # --- health ---------------------------------------------------------------------------------
    def check(self) -> bool:
        """Compare the chips with the configuration; re-initialise what was reset.

        Returns True when something had to be re-initialised. Raises :class:`DeviceIOError` when
        the MPU does not answer, :class:`WrongDeviceError` when another chip now answers."""
        self.stats["health_checks"] += 1
        self._since_health = 0
        a = self.address
        who = self._read_byte(a, R.MpuReg.WHO_AM_I)
        if R.WHO_AM_I_TABLE.get(who) != self.chip:
            raise WrongDeviceError(f"WHO_AM_I (0x75) at 0x{a:02X} now reads 0x{who:02X}, was "
                                   f"{self.chip.name}: a different device was plugged in", a,
                                   R.MpuReg.WHO_AM_I)
        pwr = self._read_byte(a, R.MpuReg.PWR_MGMT_1)
        pin = self._read_byte(a, R.MpuReg.INT_PIN_CFG)
        cfg = self.read_registers(a, R.MpuReg.SMPLRT_DIV, 5)
        if (R.SLEEP.get(pwr) or R.CLKSEL.get(pwr) != R.CLKSEL_AUTO_PLL
                or pin != self._int_pin_cfg() or cfg != self._config_bytes()):
            log.warning("MPU at 0x%02X was reset (PWR_MGMT_1=0x%02X INT_PIN_CFG=0x%02X); "
                        "re-initialising", a, pwr, pin)
            self.stats["reinits"] += 1
            self.init()
            return True
        if self.has_magnetometer:
            cntl1 = self._read_byte(R.AK8963_ADDRESS, R.AkReg.CNTL1)
            if cntl1 != self._cntl1():
                log.warning("AK8963 CNTL1 reads 0x%02X, expected 0x%02X; re-initialising it",
                            cntl1, self._cntl1())
                self.stats["reinits"] += 1
                self._init_mag()
                self._suspect, self._empty_polls, self._last_data_t = False, 0, self.clock()
                return True
        self._suspect, self._empty_polls, self._last_data_t = False, 0, self.clock()
        return False

    def _starved(self) -> bool:
        """No DRDY for 5 magnetometer periods (and several polls): the AK8963 may have reset."""
        late = self.clock() - self._last_data_t > 5.0 / self.mag_rate_hz + 0.05
        return self._empty_polls >= 3 and late

    # --- sampling -------------------------------------------------------------------------------
    def _acquire(self):
        """One poll: (t, imu bytes (14,), mag bytes (6,) or None) or None when nothing is new."""
        if self._pending_error is not None:
            e, self._pending_error = self._pending_error, None
            raise e
        if self._suspect or (self.health_every and self._since_health >= self.health_every):
            self.check()
        try:
            return self._acquire_raw()
        except DeviceIOError:
            self._suspect = True
            self.check()          # answers → re-initialised or healthy; silent → raises
            return None

    def _acquire_raw(self):
        mag = None
        if self.has_magnetometer:
            m = self.read_registers(R.AK8963_ADDRESS, R.AkReg.ST1, R.MAG_BURST_LEN)
            st1, st2 = m[0], m[-1]
            if not st1 & R.ST1_DRDY:
                self.stats["empty_polls"] += 1
                self._empty_polls += 1
                if self._starved():
                    self._suspect = True
                return None
            self._empty_polls, self._last_data_t = 0, self.clock()
            if st1 & R.ST1_DOR:
                self.stats["overruns"] += 1
            if st2 & R.ST2_HOFL:
                self.stats["overflows"] += 1
                return None
            if not st2 & R.ST2_BITM:
                self._suspect = True      # 14-bit output: the AK8963 lost its configuration
                return None
            mag = m[1:7]
        imu = self.read_registers(self.address, _IMU_BURST_START, _IMU_LEAD + R.IMU_BURST_LEN)
        if imu[0] != self._int_pin_cfg():
            self._suspect = True          # INT_PIN_CFG at its reset value: the MPU was reset
            return None
        if mag is None and not R.RAW_DATA_RDY_INT.get(imu[R.MpuReg.INT_STATUS - _IMU_BURST_START]):
            self.stats["empty_polls"] += 1    # no magnetometer to pace us: wait for new IMU data
            return None
        self.stats["samples"] += 1
        self._since_health += 1
        return self.clock(), imu[_IMU_LEAD:], mag

    def read_sample(self) -> Reading | None:
        """One sample, or None when the magnetometer has no new data (or the sample was dropped:
        overflow, reset detected). An MPU-6500 gives a sample on every call, mag NaN."""
        got = self._acquire()
        if got is None:
            return None
        block = self._decode([got])
        return Reading(float(block.t[0]), block.mag[0], block.accel[0], block.gyro[0],
                       float(block.temp[0]))

    def read_block(self, n: int, timeout: float | None = None, source: str = "",
                   poll_s: float | None = None) -> SampleBlock:
        """Up to ``n`` samples, polling every ``poll_s`` seconds while nothing is new (default
        half a magnetometer period); decoding is vectorized.

        Returns early (a shorter block) after ``timeout`` seconds on the driver clock — default
        1 s plus 2 magnetometer periods per sample — or as many empty polls, whichever comes
        first. An I/O error after some samples returns them and is raised by the next call."""
        period = 1.0 / self.mag_rate_hz if self.has_magnetometer else 1.0 / self.imu_rate_hz
        poll = period / _POLLS_PER_PERIOD if poll_s is None else poll_s
        timeout = 1.0 + 2.0 * n * period if timeout is None else timeout
        max_empty = int(timeout / poll) + 1
        got, empty, t0 = [], 0, self.clock()
        while len(got) < n and empty < max_empty and self.clock() - t0 <= timeout:
            try:
                sample = self._acquire()
            except DeviceIOError as e:
                if not got:
                    raise
                self._pending_error = e
                break
            if sample is None:
                empty += 1
                self._sleep(poll)
            else:
                got.append(sample)
        return self._decode(got, source)

    def _decode(self, got, source: str = "") -> SampleBlock:
        n = len(got)
        t = np.array([g[0] for g in got], dtype=float)
        imu = np.frombuffer(b"".join(g[1] for g in got), dtype=np.uint8).reshape(n, R.IMU_BURST_LEN)
        accel, temp, gyro = decode_imu(imu, self.accel_fs, self.gyro_fs)
        mag = np.full((n, 3), np.nan)
        if self.has_magnetometer and n:
            raw = np.frombuffer(b"".join(g[2] for g in got), dtype=np.uint8).reshape(n, 6)
            mag = decode_mag(raw, self.asa, 16)
        return SampleBlock(t=t, mag=mag, accel=accel, gyro=gyro, temp=temp, source=source)

    def close(self) -> None:
        """Put the AK8963 in power-down (best effort); the bus stays the caller's to close."""
        if self.has_magnetometer:
            try:
                self._write(R.AK8963_ADDRESS, R.AkReg.CNTL1, R.AkMode.POWER_DOWN)
            except DeviceIOError:
                pass
