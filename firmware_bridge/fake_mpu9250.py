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
import re
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from streamcal.errors import InputError

from . import registers as R

log = logging.getLogger(__name__)

_MPU_DATA = range(R.MpuReg.ACCEL_XOUT_H, R.MpuReg.ACCEL_XOUT_H + R.IMU_BURST_LEN)
_AK_SIZE = 0x13
_AK_DEFAULT_INFO = 0x9A   # INFO content is undocumented; any constant will do


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


def _rows(t: np.ndarray, values, width: int):
    """(times, values) of the rows where ``values`` is finite; values (k,width)."""
    if values is None:
        return np.empty(0), np.empty((0, width))
    v = np.asarray(values, dtype=float).reshape(len(t), width)
    ok = np.all(np.isfinite(v), axis=1)
    return t[ok], v[ok]


def _to_int16(x: np.ndarray, limit: int = 32767) -> np.ndarray:
    """Round and saturate at ±limit (-32768..32767 for the full int16 range)."""
    low = -32768 if limit == 32767 else -limit
    return np.clip(np.rint(x), low, limit).astype(np.int16)


@dataclass(frozen=True)
class EncodedRows:
    """What the chips hold for every track row: the raw counts the fake serves, per channel.

    Times are track seconds (rows where the channel is sampled). Counts are int16 as the
    registers hold them (before the driver's byte order): ``accel`` (Na,3) under ACCEL_FS_SEL
    ``accel_fs``, ``gyro`` (Ng,3) under GYRO_FS_SEL ``gyro_fs``, ``temp`` (Nt,) and ``mag``
    (Nm,3) in AK8963 axes with the fuse-ROM adjustment inverted, at ``mag_bits`` (14 or 16)
    output; ``mag_overflow`` (Nm,) bool, the rows served with ST2.HOFL (beyond full scale, or
    an injected overflow).
    """

    accel_t: np.ndarray
    accel: np.ndarray
    gyro_t: np.ndarray
    gyro: np.ndarray
    temp_t: np.ndarray
    temp: np.ndarray
    mag_t: np.ndarray
    mag: np.ndarray
    mag_overflow: np.ndarray
    accel_fs: int
    gyro_fs: int
    mag_bits: int


#: What a log without IMU columns is served as: the board at rest, flat, at room temperature.
AT_REST = {"accel": (0.0, 0.0, R.STANDARD_GRAVITY), "gyro": (0.0, 0.0, 0.0), "temp": 25.0}

_AK8963_NAMES = re.compile(r"mpu[-_ ]?92(50|55)|ak8963", re.IGNORECASE)
_BITS = re.compile(r"\b(14|16)[- ]?bit", re.IGNORECASE)


@dataclass(frozen=True)
class AkLayout:
    """How a raw-counts track holds AK8963 data: output ``bits`` (14/16), ``body_axes`` (the
    fixed remap already applied) or chip axes, fuse-ROM ``asa`` bytes, ``bits_stated``."""

    bits: int
    body_axes: bool
    asa: tuple[int, int, int]
    bits_stated: bool

    def describe(self) -> str:
        width = f"{self.bits}-bit" + ("" if self.bits_stated else ", width not stated")
        changes = (["axis remap undone"] if self.body_axes else []) \
            + (["×4 to the driver's 16-bit output"] if self.bits == 14 else [])
        served = "unchanged" if not changes else f"as the chip holds them ({', '.join(changes)})"
        asa = "/".join(str(a) for a in self.asa)
        return (f"raw AK8963 counts ({width}, {'body' if self.body_axes else 'chip'} axes) "
                f"served into HXL..HZH {served}, fuse-ROM ASA {asa}")


def _ak8963_layout(metadata: dict, where: str) -> AkLayout:
    """Read the AK8963 layout of a ``mag_unit: counts`` track from its metadata.

    Keys: ``sensor`` (or ``mag_axes``) must name an MPU-9250/9255 or AK8963; ``mag_axes`` must
    say ``chip`` or ``body`` axes; the width is ``NN-bit`` in ``sensor``/``mag_unit`` or
    ``mag_bits`` (default 16, the driver's); ``asa`` (three bytes, e.g. ``176,178,165``)
    defaults to 128 each (adjustment 1.0). Raises InputError naming ``where`` otherwise.
    """
    sensor = str(metadata.get("sensor", ""))
    axes = str(metadata.get("mag_axes", ""))
    if not _AK8963_NAMES.search(f"{sensor} {axes}"):
        said = f"# sensor: {sensor}" if sensor else "no # sensor: line"
        raise InputError(f"{where}: mag_unit is counts but the metadata does not say they are "
                         f"MPU-9250/AK8963 counts ({said}); the fake bus replays µT tracks, or raw "
                         "AK8963 counts with '# sensor: mpu9250' and '# mag_axes: AK8963 chip axes'")
    low = axes.lower()
    if "chip" in low:
        body = False
    elif "body" in low:
        body = True
    else:
        raise InputError(f"{where}: AK8963 counts but no usable '# mag_axes:' line "
                         f"({axes or 'missing'!r}): say 'AK8963 chip axes' or 'body axes'")
    stated = str(metadata.get("mag_bits", "")).strip()
    if stated:
        if stated not in ("14", "16"):
            raise InputError(f"{where}: # mag_bits: must be 14 or 16, got {stated!r}")
        bits = int(stated)
    else:
        found = {int(m.group(1)) for key in ("sensor", "mag_unit")
                 for m in _BITS.finditer(str(metadata.get(key, "")))}
        if len(found) > 1:
            raise InputError(f"{where}: the metadata states both 14-bit and 16-bit output")
        stated = "yes" if found else ""
        bits = found.pop() if found else 16
    asa = (128, 128, 128)
    if "asa" in metadata:
        try:
            values = tuple(int(v, 0) for v in re.split(r"[,\s]+", str(metadata["asa"]).strip()) if v)
        except ValueError:
            values = ()
        if len(values) != 3 or not all(0 <= v <= 255 for v in values):
            raise InputError(f"{where}: # asa: must be three fuse-ROM bytes 0..255 "
                             f"(e.g. 176,178,165), got {metadata['asa']!r}")
        asa = values
    return AkLayout(bits=bits, body_axes=body, asa=asa, bits_stated=bool(stated))


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
        if mag is not None and mag_counts is not None:
            raise ValueError("give mag (µT, body axes) or mag_counts (AK8963 counts), not both")
        if mag_counts_bits not in R.MAG_FULL_SCALE_COUNTS:
            raise ValueError(f"mag_counts_bits must be 14 or 16, got {mag_counts_bits}")
        self._mag_t, mag_body = _rows(self.t, mag, 3)
        self._mag_raw, self._mag_raw_bits = None, int(mag_counts_bits)
        if mag_counts is not None:
            self._mag_t, self._mag_raw = _rows(self.t, mag_counts, 3)
            if np.any(self._mag_raw != np.rint(self._mag_raw)):
                raise ValueError("mag_counts must be whole numbers (raw register counts)")
            mag_body = np.empty((0, 3))
        self._acc_t, self._acc = _rows(self.t, accel, 3)
        self._gyr_t, self._gyr = _rows(self.t, gyro, 3)
        self._tmp_t, tmp = _rows(self.t, temp, 1)
        self._tmp = tmp[:, 0]
        # AK8963 frame and the inverse sensitivity adjustment: counts·scale·ASA = H.
        self._mag_ak_uT = mag_body @ R.AK_TO_BODY.T   # AK_TO_BODY is its own inverse
        self._hofl_fault = self.rng.random(len(self._mag_t)) < faults.hofl_rate
        self._cache: dict = {}
        self._imu_clock_t = self._acc_t if self._acc_t.size else self._gyr_t
        dt = np.diff(self._mag_t if self._mag_t.size > 1 else self._imu_clock_t)
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
        self._mpu_power_on()
        self._ak_power_on()

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
        cols = track.columns
        metadata = dict(getattr(track, "metadata", None) or {})

        def stack(names):
            return np.column_stack([cols[n] for n in names]) if all(n in cols for n in names) \
                else None
        mag = stack(("mx", "my", "mz"))
        if mag is None:
            raise InputError(f"{where}: no mx,my,mz columns: the fake bus replays a magnetometer")
        unit = getattr(track, "mag_unit", "uT")
        notes: list[str] = []
        if unit in ("uT", "µT"):
            mag_kwargs = {"mag": mag}
        elif unit == "counts":
            layout = _ak8963_layout(metadata, where)
            counts = mag @ R.AK_TO_BODY.T if layout.body_axes else mag   # remap is self-inverse
            mag_kwargs = {"mag_counts": counts, "mag_counts_bits": layout.bits}
            kwargs.setdefault("asa", layout.asa)
            notes.append(layout.describe())
        else:
            raise InputError(
                f"{where}: mag_unit {metadata.get('mag_unit', unit)!r}: the fake bus replays µT "
                "tracks, or raw AK8963 counts of an MPU-9250 log (# mag_unit: counts with "
                "# sensor: mpu9250 … and # mag_axes: AK8963 chip axes)")
        accel = stack(("ax", "ay", "az"))
        accel_unit = getattr(track, "accel_unit", "m/s^2")
        if accel is not None and accel_unit not in ("m/s^2", "m/s2", "m/s²"):
            raise InputError(f"{where}: accel_unit {accel_unit!r}: the fake bus serves the "
                             "accelerometer in m/s²")
        imu = {"accel": accel, "gyro": stack(("gx", "gy", "gz")), "temp": cols.get("temp")}
        n = len(np.asarray(track.t))
        missing = [name for name, value in imu.items() if value is None]
        for name in missing:
            imu[name] = np.tile(np.atleast_1d(np.asarray(AT_REST[name], dtype=float)), (n, 1))
        imu["temp"] = np.asarray(imu["temp"]).reshape(-1)
        at_rest = None
        if missing:
            served = {"accel": f"accel (0, 0, {R.STANDARD_GRAVITY:g}) m/s²",
                      "gyro": "gyro 0 rad/s", "temp": f"temperature {AT_REST['temp']:g} °C"}
            at_rest = (f"no {'/'.join(missing)} in the log: serving the board at rest, "
                       f"{', '.join(served[name] for name in missing)}")
            notes.append(at_rest)
        try:
            bus = cls(track.t, **mag_kwargs, **imu, **kwargs)
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
            return self._mag_t.size == 0 or self._tau >= self._mag_t[-1]
        return self._imu_next >= len(self._imu_clock_t)

    def _sync(self) -> float:
        tau = self.now()
        while self._events and self._events[0][0] <= tau:
            _, which = self._events.pop(0)
            self.counters.resets += 1
            if which in ("mpu", "both"):
                self._mpu_power_on()
            if which in ("ak", "both"):
                self._ak_power_on()
        inside = any(a <= tau < b for a, b in self._vanish)
        if self._absent and not inside:
            self._absent = False
            self._mpu_power_on()
            self._ak_power_on()
        self._absent = inside
        if self.has_mag and self._ak_continuous() and self._clock is not None:
            self._ak_latch_until(tau)
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
            return bool(R.BYPASS_EN.get(self._mpu[R.MpuReg.INT_PIN_CFG])
                        and not R.I2C_MST_EN.get(self._mpu[R.MpuReg.USER_CTRL]))
        return False

    def _read(self, address: int, register: int, length: int) -> list[int]:
        if address == R.AK8963_ADDRESS:
            return self._ak_read(register, length)
        return self._mpu_read(register, length)

    def _write(self, address: int, register: int, data: Sequence[int]) -> None:
        for i, value in enumerate(data):
            if address == R.AK8963_ADDRESS:
                self._ak_write(self._ak_wrap(register, i), int(value) & 0xFF)
            else:
                self._mpu_write((register + i) & 0x7F, int(value) & 0xFF)

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
            accel_fs = R.ACCEL_FS_SEL.get(self._mpu[R.MpuReg.ACCEL_CONFIG])
        if gyro_fs is None:
            gyro_fs = R.GYRO_FS_SEL.get(self._mpu[R.MpuReg.GYRO_CONFIG])
        if mag_bits is None:
            mag_bits = 16 if R.AK_BIT_16.get(self._ak[R.AkReg.CNTL1]) else 14
        if accel_fs not in range(4) or gyro_fs not in range(4) or mag_bits not in R.MAG_FULL_SCALE_COUNTS:
            raise ValueError(f"accel_fs and gyro_fs must be 0..3 and mag_bits 14 or 16, got "
                             f"{accel_fs}, {gyro_fs}, {mag_bits}")
        mag, over = self._mag_counts(mag_bits)
        return EncodedRows(accel_t=self._acc_t, accel=self._imu_counts("acc", accel_fs),
                           gyro_t=self._gyr_t, gyro=self._imu_counts("gyr", gyro_fs),
                           temp_t=self._tmp_t, temp=self._imu_counts("tmp", 0)[:, 0],
                           mag_t=self._mag_t, mag=mag.astype(np.int16), mag_overflow=over,
                           accel_fs=int(accel_fs), gyro_fs=int(gyro_fs), mag_bits=int(mag_bits))

    # --- MPU-9250 die ----------------------------------------------------------------------------
    def _mpu_power_on(self) -> None:
        self._mpu = bytearray(128)
        for reg, value in R.MPU_RESET_VALUES.items():
            self._mpu[reg] = value
        self._mpu[R.MpuReg.WHO_AM_I] = self.who_am_i
        self._mpu[R.MpuReg.PWR_MGMT_1] = self.power_on_pwr_mgmt_1
        self._imu_seen = -1

    def _mpu_write(self, reg: int, value: int) -> None:
        if reg == R.MpuReg.PWR_MGMT_1 and R.H_RESET.get(value):
            self._mpu_power_on()       # H_RESET self-clears
            return
        if reg == R.MpuReg.WHO_AM_I or reg in _MPU_DATA or reg == R.MpuReg.INT_STATUS:
            return                     # read-only
        self._mpu[reg] = value

    def _mpu_read(self, reg: int, length: int) -> list[int]:
        regs = [(reg + i) & 0x7F for i in range(length)]
        view = bytearray(self._mpu)
        data = any(r in _MPU_DATA for r in regs)
        if data and self._clock is None and not self.has_mag \
                and self._imu_next < len(self._imu_clock_t):
            self._tau = self._imu_clock_t[self._imu_next]   # step mode without magnetometer
            self._imu_next += 1
        if R.MpuReg.INT_STATUS in regs:
            k = int(np.searchsorted(self._imu_clock_t, self.now(), side="right")) - 1
            ready = k > self._imu_seen and R.RAW_RDY_EN.get(self._mpu[R.MpuReg.INT_ENABLE])
            view[R.MpuReg.INT_STATUS] = R.RAW_DATA_RDY_INT.set(0, int(bool(ready)))
            self._imu_seen = k                               # cleared by this read
        if data:
            view[_MPU_DATA.start:_MPU_DATA.stop] = self._imu_bytes()
        return [view[r] for r in regs]

    def _imu_bytes(self) -> bytes:
        if R.SLEEP.get(self._mpu[R.MpuReg.PWR_MGMT_1]):
            return bytes(R.IMU_BURST_LEN)
        tau = self.now()
        afs = R.ACCEL_FS_SEL.get(self._mpu[R.MpuReg.ACCEL_CONFIG])
        gfs = R.GYRO_FS_SEL.get(self._mpu[R.MpuReg.GYRO_CONFIG])
        out = np.zeros(7, dtype=np.int16)
        for (times, key, fs), cols in zip(
                ((self._acc_t, "acc", afs), (self._tmp_t, "tmp", 0), (self._gyr_t, "gyr", gfs)),
                (slice(0, 3), slice(3, 4), slice(4, 7))):
            k = int(np.searchsorted(times, tau, side="right")) - 1
            if k >= 0:
                out[cols] = self._imu_counts(key, fs)[k]
        return out.astype(R.IMU_DTYPE).tobytes()

    def _imu_counts(self, key: str, fs: int) -> np.ndarray:
        """Raw counts of a whole channel for one full-scale setting, encoded once (vectorized)."""
        if (key, fs) not in self._cache:
            if key == "acc":
                counts = _to_int16(self._acc / R.accel_scale(fs))
            elif key == "gyr":
                counts = _to_int16(self._gyr / R.gyro_scale(fs))
            else:
                counts = _to_int16(((self._tmp - R.TEMP_ROOM_C) * R.TEMP_SENSITIVITY_LSB_PER_C
                                    + R.TEMP_ROOM_OFFSET_LSB)[:, None])
            self._cache[key, fs] = counts
        return self._cache[key, fs]

    # --- AK8963 die ------------------------------------------------------------------------------
    def _ak_power_on(self) -> None:
        self._ak = bytearray(_AK_SIZE)
        self._ak[R.AkReg.WIA] = self.ak_wia
        self._ak[R.AkReg.INFO] = _AK_DEFAULT_INFO
        self._ak_next = len(self._mag_t)     # nothing is measured until a continuous mode
        self._ak_k = -1                      # magnetometer row held in the data registers
        self._ak_drdy = self._ak_dor = self._ak_reading = False

    def _ak_mode(self) -> int:
        return R.AK_MODE.get(self._ak[R.AkReg.CNTL1])

    def _ak_continuous(self) -> bool:
        return self._ak_mode() in R.AK_CONTINUOUS_RATE_HZ

    @staticmethod
    def _ak_wrap(register: int, i: int) -> int:
        for lo, hi in R.AK_REGISTER_BLOCKS:
            if lo <= register <= hi:
                return lo + (register - lo + i) % (hi - lo + 1)
        return (register + i) % _AK_SIZE

    def _ak_write(self, reg: int, value: int) -> None:
        if reg == R.AkReg.CNTL2:
            if R.AK_SRST.get(value):
                self._ak_power_on()
            return
        if reg in (R.AkReg.CNTL1, R.AkReg.ASTC, R.AkReg.I2CDIS):
            if reg == R.AkReg.CNTL1:
                old, new = self._ak_mode(), R.AK_MODE.get(value)
                if old != R.AkMode.POWER_DOWN and new not in (R.AkMode.POWER_DOWN, old):
                    self.violations.append(f"AK8963 mode 0x{old:X} → 0x{new:X} without power-down")
                    return
                self._ak[reg] = value
                if new in R.AK_CONTINUOUS_RATE_HZ and old != new:
                    start = self.now() if self._clock is not None else self._tau
                    self._ak_next = int(np.searchsorted(self._mag_t, start, side="right"))
                return
            self._ak[reg] = value
        # WIA, INFO, ST1, data, ST2, ASA are read-only

    def _ak_latch(self, k: int, skipped: int) -> None:
        """Put magnetometer row k in the data registers; ``skipped`` rows were lost before it."""
        if self._ak_drdy:
            skipped += 1               # the unread sample is overwritten
        if skipped:
            self._ak_dor = True
            self.counters.skipped += skipped
        self._ak_k, self._ak_drdy = k, True
        self.counters.samples_latched += 1

    def _ak_latch_until(self, tau: float) -> None:
        if self._ak_reading:
            return                     # registers are protected until ST2 is read
        end = int(np.searchsorted(self._mag_t, tau, side="right"))
        if end > self._ak_next:
            self._ak_latch(end - 1, end - 1 - self._ak_next)
            self._ak_next = end

    def _ak_step(self) -> None:
        """Step mode: an ST1 poll advances to the next magnetometer sample when measuring,
        else by one magnetometer period."""
        k = self._ak_next
        if not self._ak_continuous() or k >= len(self._mag_t) or self._ak_reading:
            self._tau += self.step_dt
            self._sync()
            return
        if self.faults.dor_rate and self.rng.random() < self.faults.dor_rate \
                and k + 1 < len(self._mag_t):
            k += 1
        self._tau = self._mag_t[k]
        self._sync()
        if not self._ak_continuous():  # a reset event at this instant stopped the AK8963
            return
        self._ak_latch(k, k - self._ak_next)
        self._ak_next = k + 1

    def _ak_sample_bytes(self) -> tuple[bytes, int]:
        bits = 16 if R.AK_BIT_16.get(self._ak[R.AkReg.CNTL1]) else 14
        st2 = R.ST2_BITM if bits == 16 else 0
        if self._ak_k < 0:
            return bytes(6), st2
        counts, over = self._mag_counts(bits)
        if over[self._ak_k]:
            st2 |= R.ST2_HOFL
        return counts[self._ak_k].tobytes(), st2

    def _mag_counts(self, bits: int) -> tuple[np.ndarray, np.ndarray]:
        """(Nm,3) little-endian int16 AK8963 counts and (Nm,) HOFL flags for ``bits`` output."""
        key = ("mag", bits)
        if key not in self._cache:
            limit = R.MAG_FULL_SCALE_COUNTS[bits]
            if self._mag_raw is not None:   # recorded counts: unchanged at their own width
                raw = np.rint(self._mag_raw * (R.mag_scale(self._mag_raw_bits) / R.mag_scale(bits)))
            else:
                raw = np.rint(self._mag_ak_uT / (R.mag_scale(bits) * R.asa_factor(self.asa)))
            over = np.any(np.abs(raw) > limit, axis=1) | self._hofl_fault
            self._cache[key] = (_to_int16(raw, limit).astype(R.MAG_DTYPE), over)
        return self._cache[key]

    def _ak_read(self, reg: int, length: int) -> list[int]:
        regs = [self._ak_wrap(reg, i) for i in range(length)]
        if regs[0] == R.AkReg.ST1 and self._clock is None:
            self._ak_step()
        view = bytearray(self._ak)
        view[R.AkReg.ST1] = (R.ST1_DRDY if self._ak_drdy else 0) | (R.ST1_DOR if self._ak_dor else 0)
        data, st2 = self._ak_sample_bytes()
        view[R.AkReg.HXL:R.AkReg.HXL + 6] = data
        view[R.AkReg.ST2] = st2
        if self._ak_mode() == R.AkMode.FUSE_ROM:
            view[R.AkReg.ASAX:R.AkReg.ASAX + 3] = bytes(self.asa)
        elif any(r >= R.AkReg.ASAX for r in regs):
            self.violations.append("AK8963 fuse ROM read outside fuse-ROM mode")
        out = [view[r] for r in regs]
        if R.AkReg.ST1 in regs and self._ak_dor:
            self.counters.dor_reported += 1
        if R.AkReg.ST2 in regs:
            if self._ak_drdy and st2 & R.ST2_HOFL:
                self.counters.hofl += 1
                self.hofl_indices.append(self._ak_k)
            self._ak_drdy = self._ak_dor = self._ak_reading = False
        elif any(R.AkReg.HXL <= r < R.AkReg.ST2 for r in regs):
            self._ak_reading = True
        return out
