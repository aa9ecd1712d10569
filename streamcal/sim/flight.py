"""A simulated vehicle log with its attitude and GPS position: the truth for the attitude
reference, the mounting-rotation detection and the calibrations without a tumble.

Frames as the autopilots use them: earth NED, body forward-right-down; the attitude ``R``
turns body vectors to NED. The compass is mounted rotated by ``mount`` (sensor → body, as
:mod:`streamcal.inputs.mount_rotations` defines it) and reads, in its own frame::

    m = mountᵀ (S e + b_body + g · current) + noise

with ``e = Rᵀ B_NED`` the body-frame earth field, ``S`` a symmetric soft-iron matrix, ``b_body``
the offset and ``g`` the interference per ampere, all in the body frame. The accelerometer
reads the specific force of a vehicle without linear acceleration, ``Rᵀ (0, 0, −g)``.
``kind``:

* ``"flight"``: yaw sweeps ``turns`` times through every heading (plus a wander of ~20°), roll
  and pitch wander ±``tilt_deg``;
* ``"rover"``: the same with roll and pitch within ±``tilt_deg`` (default 2°): planar;
* ``"still"``: at rest at ``heading_deg``, level within ±0.5°.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import ATTITUDE_COLUMNS, GRAVITY
from ..inputs.track import Track
from .motion import smooth_noise

#: The default place and date: a WMM2025 field of ~48 µT, inclination ~64°.
LAT, LON, DATE = 47.3977, 8.5456, "2025-06-01"


def simulated_log(kind: str = "flight", duration_s: float = 120.0, seed: int = 0, *,
                  rate_hz: float = 10.0, b_ned=None, S=None, b_body=(12.0, -7.0, 20.0),
                  mount=None, current_gain=None, noise_uT: float = 0.3, tilt_deg=None,
                  heading_deg: float = 0.0, turns: float = 2.0, accel_noise: float = 0.05,
                  lat: float = LAT,
                  lon: float = LON, date: str = DATE) -> tuple[Track, dict]:
    """(track, truth): mag µT in the sensor frame, accel m/s² in the body frame, the attitude
    as ``att_q*`` columns, the GPS position in the metadata; ``battery_current_a`` when
    ``current_gain`` (3, µT/A in the body frame) is given.

    ``b_ned`` (3,) µT defaults to the World Magnetic Model at ``lat, lon, date``.
    ``truth``: ``{"S", "b_body", "mount", "b_ned", "yaw_deg", "current_gain"}``.
    """
    rng = np.random.default_rng(seed)
    if b_ned is None:
        from ..geomag import ned_field, parse_date, wmm_field
        b_ned = ned_field(wmm_field(lat, lon, 0.4, parse_date(date)))
    b_ned = np.asarray(b_ned, float)
    S = np.eye(3) if S is None else np.asarray(S, float)
    mount = np.eye(3) if mount is None else np.asarray(mount, float)
    n = int(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    if kind == "still":
        yaw = np.full(n, heading_deg)
        tilt = 0.5 if tilt_deg is None else tilt_deg
    else:
        yaw = heading_deg + 360.0 * turns * t / duration_s + smooth_noise(n, 1 / rate_hz, 2.0, 20.0, rng, 1)[:, 0]
        tilt = (20.0 if kind == "flight" else 2.0) if tilt_deg is None else tilt_deg
    rp = smooth_noise(n, 1 / rate_hz, 1.5, tilt / 2, rng, 2)
    rp = np.clip(rp, -tilt, tilt)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, rp[:, 1], rp[:, 0]]), degrees=True)
    e = att.inv().apply(b_ned)
    field = e @ S.T + np.asarray(b_body, float)
    aux = {}
    if current_gain is not None:
        current = np.clip(20 + 15 * np.sin(2 * np.pi * t / 30) + rng.normal(0, 1, n), 0, None)
        field = field + np.outer(current, current_gain)
        aux["battery_current_a"] = current
    mag = field @ mount + rng.normal(0, noise_uT, (n, 3))      # mountᵀ applied row-wise
    accel = att.inv().apply([0.0, 0.0, -GRAVITY]) + rng.normal(0, accel_noise, (n, 3))
    q = att.as_quat()[:, [3, 0, 1, 2]]
    aux.update(zip(ATTITUDE_COLUMNS, q.T))
    meta = {"source": f"simulated {kind} log (streamcal.sim.flight, seed {seed})",
            "gps_lat_deg": f"{lat}", "gps_lon_deg": f"{lon}", "gps_alt_m": "400",
            "gps_date": date, "gps_source": "simulated"}
    track = Track.from_arrays(t, mag=mag, accel=accel, aux=aux, metadata=meta)
    truth = {"S": S, "b_body": np.asarray(b_body, float), "mount": mount, "b_ned": b_ned,
             "yaw_deg": yaw, "current_gain": current_gain}
    return track, truth
