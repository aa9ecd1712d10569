"""The replay encoding of the fake MPU-9250 (:mod:`firmware_bridge.fake_mpu9250`): a track's
rows turned into the raw counts the chips would hold.

Accelerometer, gyro and temperature become int16 counts under a full-scale setting; the
magnetometer (µT, body axes) is turned into the AK8963's axes (the fixed remap is its own
inverse), divided by the fuse-ROM sensitivity adjustment and the output scale (14/16 bit) and
saturated, with ST2.HOFL where it overflows; a raw AK8963 counts log is kept as recorded (rescaled
exactly for the other output width). :func:`replay_arguments` reads what a
``streamcal.inputs.track.Track`` holds (µT or raw AK8963 counts, IMU columns or the board at
rest). Each channel is encoded once per setting, vectorized over the rows.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from streamcal.errors import InputError

from . import registers as R


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


def ak8963_layout(metadata: dict, where: str) -> AkLayout:
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


class Replay:
    """The track's channels, held as the chips would hold them.

    Args:
        t: (N,) seconds; mag (N,3) µT body axes or ``mag_counts`` (N,3) raw AK8963 counts in
        chip axes at ``mag_counts_bits`` output; accel (N,3) m/s²; gyro (N,3) rad/s; temp (N,)
        °C — NaN rows where a channel is not sampled. ``asa``: fuse-ROM bytes (3,).

    ``hofl_fault`` (Nm,) bool marks magnetometer rows to serve with an injected overflow (set by
    the bus from its seeded faults).
    """

    def __init__(self, t, mag=None, accel=None, gyro=None, temp=None, *, asa,
                 mag_counts=None, mag_counts_bits: int = 16):
        if mag is not None and mag_counts is not None:
            raise ValueError("give mag (µT, body axes) or mag_counts (AK8963 counts), not both")
        if mag_counts_bits not in R.MAG_FULL_SCALE_COUNTS:
            raise ValueError(f"mag_counts_bits must be 14 or 16, got {mag_counts_bits}")
        self.asa = asa
        self.mag_t, mag_body = _rows(t, mag, 3)
        self.mag_raw, self.mag_raw_bits = None, int(mag_counts_bits)
        if mag_counts is not None:
            self.mag_t, self.mag_raw = _rows(t, mag_counts, 3)
            if np.any(self.mag_raw != np.rint(self.mag_raw)):
                raise ValueError("mag_counts must be whole numbers (raw register counts)")
            mag_body = np.empty((0, 3))
        self.acc_t, self.acc = _rows(t, accel, 3)
        self.gyr_t, self.gyr = _rows(t, gyro, 3)
        self.tmp_t, tmp = _rows(t, temp, 1)
        self.tmp = tmp[:, 0]
        # AK8963 frame and the inverse sensitivity adjustment: counts·scale·ASA = H.
        self.mag_ak_uT = mag_body @ R.AK_TO_BODY.T   # AK_TO_BODY is its own inverse
        self.hofl_fault = np.zeros(len(self.mag_t), bool)
        self._cache: dict = {}

    def imu_counts(self, key: str, fs: int) -> np.ndarray:
        """Raw counts of a whole channel (``acc``, ``gyr``, ``tmp``) for one full-scale
        setting, (n,3) or (n,1) int16, encoded once."""
        if (key, fs) not in self._cache:
            if key == "acc":
                counts = _to_int16(self.acc / R.accel_scale(fs))
            elif key == "gyr":
                counts = _to_int16(self.gyr / R.gyro_scale(fs))
            else:
                counts = _to_int16(((self.tmp - R.TEMP_ROOM_C) * R.TEMP_SENSITIVITY_LSB_PER_C
                                    + R.TEMP_ROOM_OFFSET_LSB)[:, None])
            self._cache[key, fs] = counts
        return self._cache[key, fs]

    def mag_counts(self, bits: int) -> tuple[np.ndarray, np.ndarray]:
        """(Nm,3) little-endian int16 AK8963 counts and (Nm,) HOFL flags for ``bits`` output."""
        key = ("mag", bits)
        if key not in self._cache:
            limit = R.MAG_FULL_SCALE_COUNTS[bits]
            if self.mag_raw is not None:   # recorded counts: unchanged at their own width
                raw = np.rint(self.mag_raw * (R.mag_scale(self.mag_raw_bits) / R.mag_scale(bits)))
            else:
                raw = np.rint(self.mag_ak_uT / (R.mag_scale(bits) * R.asa_factor(self.asa)))
            over = np.any(np.abs(raw) > limit, axis=1) | self.hofl_fault
            self._cache[key] = (_to_int16(raw, limit).astype(R.MAG_DTYPE), over)
        return self._cache[key]

    def encoded_rows(self, accel_fs: int, gyro_fs: int, mag_bits: int) -> EncodedRows:
        """Every row's raw counts under these settings (:class:`EncodedRows`)."""
        if accel_fs not in range(4) or gyro_fs not in range(4) or mag_bits not in R.MAG_FULL_SCALE_COUNTS:
            raise ValueError(f"accel_fs and gyro_fs must be 0..3 and mag_bits 14 or 16, got "
                             f"{accel_fs}, {gyro_fs}, {mag_bits}")
        mag, over = self.mag_counts(mag_bits)
        return EncodedRows(accel_t=self.acc_t, accel=self.imu_counts("acc", accel_fs),
                           gyro_t=self.gyr_t, gyro=self.imu_counts("gyr", gyro_fs),
                           temp_t=self.tmp_t, temp=self.imu_counts("tmp", 0)[:, 0],
                           mag_t=self.mag_t, mag=mag.astype(np.int16), mag_overflow=over,
                           accel_fs=int(accel_fs), gyro_fs=int(gyro_fs), mag_bits=int(mag_bits))


def replay_arguments(track, where: str) -> tuple[dict, list[str], str | None, tuple | None]:
    """What :meth:`FakeMPU9250Bus.from_track` passes on: (channel keyword arguments, notes on
    how the track was read, the at-rest note or None, the fuse-ROM bytes a counts log states
    or None). Raises InputError naming ``where`` for what cannot be replayed."""
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
    asa = None
    if unit in ("uT", "µT"):
        channels = {"mag": mag}
    elif unit == "counts":
        layout = ak8963_layout(metadata, where)
        counts = mag @ R.AK_TO_BODY.T if layout.body_axes else mag   # remap is self-inverse
        channels = {"mag_counts": counts, "mag_counts_bits": layout.bits}
        asa = layout.asa
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
    return {**channels, **imu}, notes, at_rest, asa
