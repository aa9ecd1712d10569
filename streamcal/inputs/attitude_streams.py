"""The vehicle's logged attitude and GPS position, from autopilot logs, for the attitude
reference (:mod:`streamcal.fitting.attitude_reference`).

Attitude becomes the track columns ``att_qw, att_qx, att_qy, att_qz``
(:data:`streamcal.constants.ATTITUDE_COLUMNS`): the unit quaternion, scalar first, that turns
body-frame (forward-right-down) vectors into the local NED frame, signs kept on one hemisphere
from sample to sample so that linear interpolation between samples stays a rotation after
normalising. The position is not a column: its median over the samples with a 3-D fix goes into
the metadata (``gps_lat_deg``, ``gps_lon_deg``, ``gps_alt_m`` above mean sea level,
``gps_date`` from the GPS clock, ``gps_source``).

ArduPilot: ``ATT`` Roll/Pitch/Yaw (degrees; the EKF's attitude), else ``AHR2``; Euler angles
in the aerospace z-y-x order, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (ArduPilot's
``Matrix3::from_euler``). ``GPS`` Lat/Lng (degrees), Alt (m), Status ≥ 3 (3-D fix); the date
from the GPS week and milliseconds of the week (``Week``/``TimeMS`` in old layouts, ``GWk``/
``GMS`` in newer ones), counted from 1980-01-06 (leap seconds ignored: a date is needed only
to the day).

PX4: ``vehicle_attitude.q[0..3]`` (w, x, y, z: body FRD → NED, as PX4 defines it);
``vehicle_gps_position`` or ``sensor_gps`` (``lat``/``lon`` 1e-7 degrees and ``alt`` mm, or
``latitude_deg``/``longitude_deg``/``altitude_msl_m``; ``fix_type`` ≥ 3; ``time_utc_usec`` for
the date), else ``vehicle_global_position`` (``lat``/``lon`` degrees, ``alt`` m; no date).
"""
from __future__ import annotations

import datetime as _dt

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import ATTITUDE_COLUMNS
from .streams import Stream

#: Messages of a DataFlash log these functions read (added to the reader's list).
DATAFLASH_MESSAGES = ("ATT", "AHR2", "GPS")
GPS_EPOCH = _dt.date(1980, 1, 6)
FIX_3D = 3


def continuous_quaternions(q_wxyz: np.ndarray) -> np.ndarray:
    """``q`` (N,4) with signs flipped so that consecutive quaternions have a non-negative dot
    product (the same rotations; linear interpolation between neighbours then stays short)."""
    q = np.asarray(q_wxyz, dtype=float)
    if len(q) < 2:
        return q
    dots = np.einsum("ij,ij->i", q[1:], q[:-1])
    signs = np.cumprod(np.r_[1.0, np.where(dots < 0, -1.0, 1.0)])
    return q * signs[:, None]


def euler_to_quaternions(roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """(N,4) scalar-first quaternions of ``Rz(yaw) Ry(pitch) Rx(roll)`` (degrees)."""
    angles = np.column_stack([yaw_deg, pitch_deg, roll_deg]).astype(float)
    xyzw = Rotation.from_euler("ZYX", angles, degrees=True).as_quat()
    return continuous_quaternions(xyzw[:, [3, 0, 1, 2]])


def _attitude_stream(name: str, t: np.ndarray, q: np.ndarray, meta: dict, source: str):
    ok = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    if not ok.any():
        return None
    meta["attitude_source"] = source
    return Stream(name, t[ok], dict(zip(ATTITUDE_COLUMNS, continuous_quaternions(q[ok]).T)))


def _position_meta(meta: dict, lat, lon, alt, date: _dt.date | None, source: str) -> None:
    """Median position of the fixes into ``meta``; nothing when none is a real position."""
    lat, lon, alt = (np.asarray(v, dtype=float) for v in (lat, lon, alt))
    ok = np.isfinite(lat) & np.isfinite(lon) & ((lat != 0) | (lon != 0)) & (np.abs(lat) <= 90)
    if not ok.any():
        return
    meta["gps_lat_deg"] = f"{np.median(lat[ok]):.7f}"
    meta["gps_lon_deg"] = f"{np.median(lon[ok]):.7f}"
    alt_ok = ok & np.isfinite(alt)
    meta["gps_alt_m"] = f"{np.median(alt[alt_ok]):.1f}" if alt_ok.any() else "0"
    if date is not None:
        meta["gps_date"] = date.isoformat()
    meta["gps_source"] = f"{source}, median of {int(ok.sum())} fixes"


def gps_week_date(week: float, ms_of_week: float) -> _dt.date | None:
    """The UTC day of GPS ``week`` and ``ms_of_week`` (None when week is 0 or not finite)."""
    if not (np.isfinite(week) and week > 0 and np.isfinite(ms_of_week)):
        return None
    return GPS_EPOCH + _dt.timedelta(days=7 * int(week), milliseconds=float(ms_of_week))


def dataflash_attitude(msgs, time_of, meta: dict) -> list[Stream]:
    """ATT (else AHR2) as attitude quaternion columns and the GPS position into ``meta``.

    ``msgs`` is the DataFlash reader's message table (``has``, ``count``, ``array``),
    ``time_of(name)`` gives a message's boot time in seconds.
    """
    out = []
    for name in ("ATT", "AHR2"):
        if msgs.count(name) and msgs.has(name, "Roll", "Pitch", "Yaw"):
            q = euler_to_quaternions(*(msgs.array(name, c) for c in ("Roll", "Pitch", "Yaw")))
            stream = _attitude_stream(name, time_of(name), q, meta,
                                      f"{name}.Roll/Pitch/Yaw (deg, z-y-x Euler, body FRD to NED)")
            if stream is not None:
                out.append(stream)
                break
    if msgs.count("GPS") and msgs.has("GPS", "Lat", "Lng"):
        keep = np.ones(msgs.count("GPS"), dtype=bool)
        if msgs.has("GPS", "I"):
            keep &= msgs.array("GPS", "I") == 0
        if msgs.has("GPS", "Status"):
            keep &= msgs.array("GPS", "Status") >= FIX_3D
        if keep.any():
            week_ms = next(((w, m) for w, m in (("GWk", "GMS"), ("Week", "TimeMS"))
                            if msgs.has("GPS", w, m)), None)
            date = None
            if week_ms is not None:
                k = int(np.flatnonzero(keep)[-1])
                date = gps_week_date(msgs.array("GPS", week_ms[0])[k],
                                     msgs.array("GPS", week_ms[1])[k])
            alt = msgs.array("GPS", "Alt")[keep] if msgs.has("GPS", "Alt") \
                else np.zeros(int(keep.sum()))
            _position_meta(meta, msgs.array("GPS", "Lat")[keep], msgs.array("GPS", "Lng")[keep],
                           alt, date, "GPS.Lat/Lng/Alt (3-D fixes)")
    return out


def _ulog_topic(ulog, name: str):
    found = [d for d in ulog.data_list if d.name == name]
    return min(found, key=lambda d: d.multi_id) if found else None


def ulog_attitude(ulog, meta: dict) -> list[Stream]:
    """vehicle_attitude as attitude quaternion columns and the GPS position into ``meta``."""
    out = []
    d = _ulog_topic(ulog, "vehicle_attitude")
    if d is not None and all(f"q[{i}]" in d.data for i in range(4)):
        q = np.column_stack([d.data[f"q[{i}]"].astype(np.float64) for i in range(4)])
        stream = _attitude_stream("vehicle_attitude", d.data["timestamp"] * 1e-6, q, meta,
                                  "vehicle_attitude.q (w,x,y,z; body FRD to NED)")
        if stream is not None:
            out.append(stream)
    for name in ("vehicle_gps_position", "sensor_gps"):
        d = _ulog_topic(ulog, name)
        if d is None:
            continue
        data = d.data
        fix = data["fix_type"] >= FIX_3D if "fix_type" in data else \
            np.ones(len(data["timestamp"]), dtype=bool)
        if "latitude_deg" in data:
            lat, lon = data["latitude_deg"], data["longitude_deg"]
            alt = data.get("altitude_msl_m", np.zeros(len(lat)))
        elif "lat" in data:
            lat, lon = data["lat"] * 1e-7, data["lon"] * 1e-7
            alt = data["alt"] * 1e-3 if "alt" in data else np.zeros(len(lat))
        else:
            continue
        if not fix.any():
            continue
        date = None
        utc = data.get("time_utc_usec")
        if utc is not None and np.any(utc[fix] > 0):
            last = float(utc[fix][utc[fix] > 0][-1])
            date = _dt.datetime.fromtimestamp(last * 1e-6, _dt.timezone.utc).date()
        _position_meta(meta, lat[fix], lon[fix], alt[fix], date,
                       f"{name} (3-D fixes)")
        if "gps_lat_deg" in meta:
            return out
    d = _ulog_topic(ulog, "vehicle_global_position")
    if d is not None and "lat" in d.data:
        _position_meta(meta, d.data["lat"], d.data["lon"], d.data.get("alt", 0 * d.data["lat"]),
                       None, "vehicle_global_position")
    return out
