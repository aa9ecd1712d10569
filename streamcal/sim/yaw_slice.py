"""A yaw-mostly slice with a gyro: a drone or robot turning about the vertical, tilting a little.

    from streamcal.sim.yaw_slice import yaw_slice
    res = yaw_slice(60, seed=1, K=K, b=b, tilt_deg=10)
    res.track, res.truth.K, res.truth.b

The body turns about the world vertical (yaw ψ, a smooth random rate around a mean, so it goes
round several times) and tilts by roll φ and pitch θ of amplitude ``tilt_deg`` (smooth random,
a sum of three sinusoids of random frequency in :data:`WOBBLE_HZ` and phase). Body → world rotation Rz(ψ) Ry(θ) Rx(φ); the body rate ω is from the
orientation path (centred differences on a 1 ms grid). The field direction in the body is
h = Rᵀ f/‖f‖ (Earth field of ``field_uT`` µT, ``dip_deg`` below the horizon), the reading
m = K h + b + noise (µT); the gyro reads (1 + gain) ⊙ ω + bias + noise (rad/s), the
accelerometer the gravity in the body (m/s², no linear acceleration). With ``tilt_deg`` = 0 the
rotation is about the body z axis only.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .motion import Motion, rate_at_nodes, smooth_noise

#: Frequencies (Hz) of the bounded tilt/yaw wobble.
WOBBLE_HZ = (0.1, 0.5)
from .scenario import SimResult, SimTruth, assemble_track
from .sensor import earth_field


def yaw_slice(duration_s: float = 60.0, seed: int = 0, *, K, b, noise_uT: float = 0.4,
              tilt_deg: float = 10.0, yaw_rate: float = 0.6, rate_sd: float = 0.4,
              gyro_noise: float = 0.005, gyro_bias=(0.004, -0.006, 0.003),
              gyro_gain=(0.005, -0.004, 0.006), field_uT: float = 48.0, dip_deg: float = 60.0,
              mag_rate_hz: float = 100.0, imu_rate_hz: float = 200.0,
              yaw_deg: float | None = None) -> SimResult:
    """Simulate the slice (module doc); ``K`` (3,3), ``b`` (3,) µT the true sensor model,
    ``yaw_rate`` the mean yaw rate (rad/s), ``rate_sd`` the spread of the yaw and tilt rates,
    ``gyro_noise`` rad/s per axis; ``yaw_deg``: when given, the yaw is bounded to ± that
    (like the tilt: a hovering board) instead of turning round."""
    rng = np.random.default_rng(seed)
    K, b = np.asarray(K, float), np.asarray(b, float)
    dt = 1e-3
    tg = np.arange(-1.0, duration_s + 1.0 + dt, dt)
    n = len(tg)
    psi = np.cumsum(yaw_rate + smooth_noise(n, dt, 1.0, rate_sd, rng)[:, 0]) * dt
    if yaw_deg is not None:
        psi = _wobble(tg, np.radians(yaw_deg), rng)
    tilt = np.column_stack([_wobble(tg, np.radians(tilt_deg), rng) for _ in range(2)])
    rot = Rotation.from_euler("ZYX", np.column_stack([psi, tilt[:, 1], tilt[:, 0]]))
    # scipy's composition here, not motion.py's quaternion product: that one differs in the
    # last bits (≈ 1e-13 rad/s), and the seeds' tracks are kept as they were
    step = (rot[:-1].inv() * rot[1:]).as_rotvec() / dt
    motion = Motion(tg, Rotation.from_quat(rot.as_quat()), rate_at_nodes(step),
                    np.zeros((n, 3)), np.ones(n))

    t_mag = np.arange(0.0, duration_s, 1.0 / mag_rate_hz)
    t_imu = np.arange(0.0, duration_s, 1.0 / imu_rate_hz) + 0.25 / imu_rate_hz
    to_body_mag = motion.at(t_mag)[0].inv()
    to_world_imu, w, _ = motion.at(t_imu)
    f = earth_field(field_uT, dip_deg)
    h = to_body_mag.apply(f / field_uT)
    mag = h @ K.T + b + noise_uT * rng.standard_normal(h.shape)
    gyro = w * (1.0 + np.asarray(gyro_gain)) + np.asarray(gyro_bias) + \
        gyro_noise * rng.standard_normal(w.shape)
    accel = to_world_imu.inv().apply([0.0, 0.0, 9.80665])
    temp = np.full(len(t_imu), 25.0)
    meta = {"sensor": "mpu9250", "source": f"yaw slice seed {seed}", "simulated": "yes",
            "seed": str(seed), "mag_unit": "uT"}
    track = assemble_track(t_mag, mag, t_imu, accel, gyro, temp, {}, meta)
    truth = SimTruth(K=K, b=b, field_uT=float(field_uT), dip_deg=float(dip_deg),
                     field_world=f, effects={}, mag_lsb=np.zeros(3), noise_uT=float(noise_uT),
                     imu={"gyro_b": np.asarray(gyro_bias), "gyro_S": 1 + np.asarray(gyro_gain)},
                     outlier_spans=np.empty((0, 2)), seed=int(seed), t_mag=t_mag,
                     t_sample=t_mag, directions=h, directions_body=h,
                     up_body=to_body_mag.apply([0.0, 0.0, 1.0]), mag_clean=h @ K.T + b,
                     disturbance=np.zeros_like(h), temp=np.full(len(t_mag), 25.0),
                     motor_current=np.zeros(len(t_mag)))
    return SimResult(track, truth)


def _wobble(t: np.ndarray, amp: float, rng: np.random.Generator) -> np.ndarray:
    """(G,) angle bounded by ``amp`` rad: three sinusoids of amplitude amp/3."""
    f = rng.uniform(*WOBBLE_HZ, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    return amp / 3 * np.sum(np.sin(2 * np.pi * f * t[:, None] + ph), axis=1)
