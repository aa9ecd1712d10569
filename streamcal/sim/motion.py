"""Hand motion of the board: orientation, body angular velocity and linear acceleration.

Frames: the world frame is East-North-Up (ENU, z up); the body frame is the accelerometer/gyro
frame of the board. ``rotation`` maps body vectors to world vectors (``v_world = R v_body``), so a
world field is seen in the body frame as ``R⁻¹ B``.

Motion is generated on a uniform internal grid (``dt`` seconds, starting before t = 0 so that
lagged instants exist) and evaluated at any sample instant by spherical interpolation
(:meth:`Motion.at`). Everything is vectorized over time: rates are filtered noise
(:func:`smooth_noise`, a second-order Ornstein–Uhlenbeck process), orientations are integrated
by a parallel prefix product of the per-step rotations (:func:`cumulative_rotation`).

Coverage patterns (the set of unit field directions ``x = R⁻¹ B̂`` seen in the body frame):

============== ====================================================================== ==========
``full``       hand tumble: random body rates, directions fill the sphere S²
``hemisphere`` body z stays within 90° of the field: ``x_z ≥ 0``
``planar``     board flat on a table turned about the vertical: ``x_z = −sin(dip)``
``band``       board rolled about the east axis, wobbling ±``band_deg``:
               ``|x_z| ≤ sin(band_deg)``
============== ====================================================================== ==========
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation, Slerp

from ..quaternion import cumulative_rotation, qmul

COVERAGES = ("full", "hemisphere", "planar", "band")


def smooth_noise(n: int, dt: float, tau: float, sigma: float, rng: np.random.Generator,
                 dims: int = 3) -> np.ndarray:
    """(n, dims) stationary second-order Ornstein–Uhlenbeck noise: white noise through two
    identical first-order low-passes of time constant ``tau`` (s), scaled to standard deviation
    ``sigma``. Its derivative is continuous, unlike a first-order OU path."""
    a = np.exp(-dt / tau)
    burn = int(np.ceil(8 * tau / dt))
    w = rng.standard_normal((n + burn, dims))
    y = lfilter([1.0 - a * a], [1.0, -a], lfilter([1.0], [1.0, -a], w, axis=0), axis=0)
    # Impulse response h_k = (1−a²)(k+1)aᵏ has Σh² = (1+a²)/(1−a²).
    return sigma * np.sqrt((1 - a * a) / (1 + a * a)) * y[burn:]


def activity_envelope(t: np.ndarray, pauses: np.ndarray, edge_s: float = 0.3) -> np.ndarray:
    """(G,) motion envelope in [0, 1]: 0 inside each still interval ``pauses`` (P,2) [s],
    1 away from them, raised-cosine transitions of ``edge_s`` seconds outside each interval."""
    still = np.zeros_like(t)
    for start, end in np.asarray(pauses, dtype=float).reshape(-1, 2):  # loop over pauses only
        d = np.maximum(start - t, t - end)  # distance outside the pause, <= 0 inside
        w = np.where(d <= 0, 1.0, 0.5 * (1 + np.cos(np.pi * np.clip(d / edge_s, 0, 1))))
        still = np.maximum(still, w)
    return 1.0 - still


def _tilt(theta1: np.ndarray, theta2: np.ndarray, max_rad: float) -> Rotation:
    """Tilt about a horizontal axis: magnitude ``max_rad·|sin θ1|`` (≤ max_rad), azimuth θ2;
    smooth in (θ1, θ2)."""
    r = max_rad * np.sin(theta1)
    return Rotation.from_rotvec(np.stack([r * np.cos(theta2), r * np.sin(theta2),
                                          np.zeros_like(r)], axis=1))


def _about_z(angle: np.ndarray) -> Rotation:
    """Rotations by ``angle`` (G,) rad about +z."""
    return Rotation.from_rotvec(np.outer(angle, [0.0, 0.0, 1.0]))


def _align_z_to(axis: np.ndarray) -> Rotation:
    """A rotation taking world +z onto the unit vector ``axis``."""
    rot, _ = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])
    return rot


@dataclass(frozen=True)
class Motion:
    """Board motion sampled on a uniform grid.

    Attributes:
        t: (G,) grid instants, s.
        rotation: G body→world rotations.
        omega: (G,3) body-frame angular velocity, rad/s.
        accel: (G,3) world-frame linear acceleration (gravity excluded), m/s².
        envelope: (G,) activity in [0, 1]; 0 where the board is still.
    """

    t: np.ndarray
    rotation: Rotation
    omega: np.ndarray
    accel: np.ndarray
    envelope: np.ndarray

    @cached_property
    def _slerp(self) -> Slerp:
        return Slerp(self.t, self.rotation)

    def at(self, t: np.ndarray) -> tuple[Rotation, np.ndarray, np.ndarray]:
        """Orientation (slerp), body rate and linear acceleration (linear interpolation) at the
        instants ``t`` (M,) s, which must lie inside the grid."""
        t = np.asarray(t, dtype=float)
        rot = self._slerp(t)
        omega = np.stack([np.interp(t, self.t, self.omega[:, i]) for i in range(3)], axis=1)
        accel = np.stack([np.interp(t, self.t, self.accel[:, i]) for i in range(3)], axis=1)
        return rot, omega, accel


def hand_motion(t0: float, t1: float, rng: np.random.Generator, *, coverage: str = "full",
                field_dir: np.ndarray, dt: float = 1e-3, rate_rad_s: float = 1.0,
                rate_tau_s: float = 0.5, pauses: np.ndarray | None = None,
                lin_accel_m_s2: float = 0.4, band_deg: float = 20.0) -> Motion:
    """Simulate a board turned by hand from ``t0`` to ``t1`` seconds.

    Args:
        coverage: one of :data:`COVERAGES` (see the module docstring for the direction sets).
        field_dir: (3,) unit Earth-field direction in the world (ENU) frame.
        dt: grid step, s.
        rate_rad_s: per-axis standard deviation of the hand's angular rate, rad/s.
        rate_tau_s: correlation time of the rates, s.
        pauses: (P,2) intervals [s] where the board is still (rates and acceleration are 0).
        lin_accel_m_s2: per-axis standard deviation of the linear acceleration while moving.
        band_deg: half-width of the ``band`` pattern, degrees.
    """
    if coverage not in COVERAGES:
        raise ValueError(f"coverage must be one of {', '.join(COVERAGES)}, found {coverage!r}")
    n = int(np.ceil((t1 - t0) / dt)) + 1
    t = t0 + dt * np.arange(n)
    env = activity_envelope(t, np.empty((0, 2)) if pauses is None else pauses)
    rates = env[:, None] * smooth_noise(n, dt, rate_tau_s, rate_rad_s, rng)
    accel = env[:, None] * smooth_noise(n, dt, 0.3, lin_accel_m_s2, rng)
    start = Rotation.random(random_state=rng)

    if coverage == "full":
        mid = 0.5 * (rates[:-1] + rates[1:])
        steps = cumulative_rotation(Rotation.from_rotvec(mid * dt))
        rotation = Rotation.concatenate([start, start * steps])
        return Motion(t, rotation, rates, accel, env)

    # Scripted patterns: angles are integrals of the (paused) rates, so they stop when still.
    angles = np.cumsum(rates, axis=0) * dt + rng.uniform(0, 2 * np.pi, 3)
    if coverage == "planar":
        chain = [_about_z(angles[:, 0])]
    elif coverage == "band":
        east = np.cross(field_dir, [0.0, 0.0, 1.0])
        east = east / np.linalg.norm(east) if np.linalg.norm(east) > 1e-9 else np.array([1.0, 0, 0])
        chain = [_align_z_to(east), _about_z(angles[:, 0]),
                 _tilt(angles[:, 1], angles[:, 2], np.radians(band_deg))]
    else:  # hemisphere: three angles move at once, so each goes slower
        angles = 0.6 * angles
        chain = [_align_z_to(field_dir), _about_z(angles[:, 0]),
                 _tilt(angles[:, 1], 1.3 * angles[:, 0], np.pi / 2), _about_z(0.7 * angles[:, 2])]
    q = chain[0].as_quat()
    for r in chain[1:]:
        q = qmul(q, r.as_quat())
    q = np.broadcast_to(q, (n, 4))
    # Body rate from the orientation path: ω_k ≈ log(R_kᵀ R_{k+1}) / dt, centred.
    conj = q[:-1] * np.array([-1.0, -1.0, -1.0, 1.0])
    step = Rotation.from_quat(qmul(conj, q[1:])).as_rotvec() / dt
    return Motion(t, Rotation.from_quat(q), rate_at_nodes(step), accel, env)


def rate_at_nodes(step: np.ndarray) -> np.ndarray:
    """(G,3) body rate (rad/s) at the grid instants from the mean rates over the G−1 steps
    between them (G−1,3): the average of the two steps around an inner instant (centred), the
    one step at either end."""
    omega = np.empty((len(step) + 1, 3))
    omega[1:-1] = 0.5 * (step[:-1] + step[1:])
    omega[0], omega[-1] = step[0], step[-1]
    return omega
