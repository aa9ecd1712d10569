"""A recording session: motion, environment, sensor errors and effects → a Track plus its truth.

Everything random comes from independent streams spawned from one seed (motion, board errors,
effect parameters, noise, bursts, auxiliary channel, timestamps), so switching an effect on or off
changes the data by exactly that effect's term while the motion and the noise stay the same.

Sampling: the sensors sample on their own regular clocks (mag ``mag_rate_hz``, IMU
``imu_rate_hz``); the host stamps each sample with a small jitter; mag and IMU samples go to
separate rows with empty cells (NaN) for the columns not sampled (docs/tracks_and_inputs.md).
Temperature and the ``motor_current`` auxiliary channel ride on the IMU rows.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError, UnknownEffectError
from ..inputs.track import Track
from ..model.catalog import BY_NAME, CORE_EFFECTS, EFFECT_NAMES, SIMULATED_EFFECTS
from ..model.declaration import SimEnvironment
from . import sensor
from .motion import COVERAGES, hand_motion

GENERATOR = "streamcal.sim/1"
TEMP_PROFILES = ("constant", "warmup", "ramp", "cycle")
#: Decimals written per column: below the quantization step, so rounding loses nothing real.
DECIMALS = {"t": 5, "mx": 3, "my": 3, "mz": 3, "ax": 4, "ay": 4, "az": 4,
            "gx": 5, "gy": 5, "gz": 5, "temp": 3, "motor_current": 3}
#: Reference temperature (°C) and time (s) of the simulated effects; b and K hold at T0, t0.
T0_C = 25.0
T0_S = 0.0
JITTER_S = 50e-6
ACCEL_NOISE = 8e-3 * sensor.G        # 8 mg rms, HARDWARE.md §5
GYRO_NOISE = np.radians(0.1)         # 0.1 °/s rms, HARDWARE.md §5
TEMP_NOISE_C = 0.02
CURRENT_NOISE_A = 0.005


@dataclass(frozen=True, eq=False)
class SimTruth:
    """What the simulator knows and a fitter should find.

    Global parameters:
        K: (3,3) upper triangular, µT; b: (3,) µT (both at ``T0 = 25 °C``, ``t0 = 0 s``).
        field_uT: Earth field strength; dip_deg: inclination below the horizon, degrees.
        field_world: (3,) field in the ENU world frame, µT.
        effects: parameters of the switched-on effects in the calibration-file layout of
            :mod:`streamcal.model` (``{"temperature_offset": {"T0": .., "c": [..]}, …}``).
        mag_lsb: (3,) quantization step per axis after the fuse-ROM adjustment, µT.
        noise_uT: magnetometer white noise per axis, µT.
        imu: accelerometer/gyro errors (:func:`streamcal.sim.sensor.imu_errors`), plus
            ``accel_K`` (3,3) = ``G·accel_S`` and ``accel_b`` in the same model form as the mag.
        outlier_spans: (B,2) [t_start, t_end] stamps (s) of the disturbing bursts; the
            disturbance is exactly zero outside them.
        seed: the seed of the run.

    Per magnetometer sample (M rows, the track's mag rows in order):
        t_mag: (M,) stamps, s; t_sample: (M,) true sampling instants, s (``t_mag − τ − jitter``).
        directions: (M,3) unit field directions in the magnetometer frame (``u = K x``).
        directions_body: (M,3) the same in the accel/gyro (body) frame.
        up_body: (M,3) the world's up (−gravity) direction in the body frame.
        mag_clean: (M,3) ``K x + b + effect terms``, µT: no noise, burst or quantization.
        disturbance: (M,3) reading added by the bursts, µT.
        temp: (M,) true temperature at the sampling instants, °C.
        motor_current: (M,) true motor current at the sampling instants, A.
    """

    K: np.ndarray
    b: np.ndarray
    field_uT: float
    dip_deg: float
    field_world: np.ndarray
    effects: dict
    mag_lsb: np.ndarray
    noise_uT: float
    imu: dict
    outlier_spans: np.ndarray
    seed: int
    t_mag: np.ndarray
    t_sample: np.ndarray
    directions: np.ndarray
    directions_body: np.ndarray
    up_body: np.ndarray
    mag_clean: np.ndarray
    disturbance: np.ndarray
    temp: np.ndarray
    motor_current: np.ndarray

    @property
    def outlier_mask(self) -> np.ndarray:
        """(M,) True for mag samples stamped inside an outlier span."""
        s = self.outlier_spans
        return np.any((self.t_mag[:, None] >= s[:, 0]) & (self.t_mag[:, None] <= s[:, 1]), axis=1)

    def to_dict(self) -> dict:
        """JSON-able global parameters (the per-sample arrays are left out)."""
        return {"K": self.K.tolist(), "b": self.b.tolist(), "field_uT": self.field_uT,
                "dip_deg": self.dip_deg, "effects": self.effects, "mag_lsb": self.mag_lsb.tolist(),
                "noise_uT": self.noise_uT, "outlier_spans": self.outlier_spans.tolist(),
                "imu": {k: np.asarray(v).tolist() for k, v in self.imu.items()}, "seed": self.seed}


@dataclass(frozen=True, eq=False)
class SimResult:
    """``track``: the simulated :class:`streamcal.inputs.track.Track`; ``truth``: :class:`SimTruth`."""

    track: Track
    truth: SimTruth

    def write(self, path, truth_path=None) -> None:
        """Write the track (``.csv`` or ``.csv.gz``, atomic) and, if asked, the truth's global
        parameters as JSON (atomic)."""
        self.track.write(path)
        if truth_path is not None:
            from ..atomic import atomic_write_text
            atomic_write_text(truth_path, json.dumps(self.truth.to_dict(), indent=2))


def simulate(duration_s: float = 300.0, seed: int = 0, effects: Mapping[str, Any] | None = None,
             *, noise_uT: float = 0.4, mag_bits: int = 16, mag_rate_hz: float = 100.0,
             imu_rate_hz: float = 200.0, coverage: str = "full", outlier_bursts: int = 0,
             burst_uT: float = 150.0, field_uT: float = 48.0, dip_deg: float = 60.0,
             K: np.ndarray | None = None, b: np.ndarray | None = None,
             temp_profile: str = "warmup", temp_start_c: float = 22.0, temp_delta_c: float = 6.0,
             motor: bool = True, pause_fraction: float = 0.1, rate_rad_s: float = 1.0,
             band_deg: float = 20.0, metadata: Mapping[str, str] | None = None) -> SimResult:
    """Simulate an MPU-9250 turned by hand and return its track and the truth.

    Args:
        duration_s: length of the recording, s.
        seed: everything is deterministic per seed.
        effects: ``{effect name: magnitude}`` of docs/effects.md effects to switch on (see
            :mod:`streamcal.sim.sensor` for each term and its magnitude's unit); a 3-vector
            parameter may be given as a (3,) sequence instead of a magnitude.
        noise_uT: magnetometer white noise per axis, µT.
        mag_bits: AK8963 output width, 16 (0.15 µT/LSB) or 14 (0.6 µT/LSB).
        mag_rate_hz, imu_rate_hz: sample rates, Hz (rows are written per docs/tracks_and_inputs.md).
        coverage: ``full``, ``hemisphere``, ``planar`` or ``band`` (:mod:`streamcal.sim.motion`).
        outlier_bursts: number of magnets/phones passing by, each a few seconds long with a peak
            disturbance of ``burst_uT`` µT.
        field_uT, dip_deg: Earth field strength (µT) and inclination (degrees below horizon).
        K, b: the true sensor model (µT); drawn at random per seed when None. K must be upper
            triangular with a positive diagonal.
        temp_profile: ``constant``, ``warmup`` (exponential, time constant duration/4), ``ramp``
            (linear) or ``cycle`` (up and back down, sin(π t/duration)); from ``temp_start_c``
            by ``temp_delta_c`` °C.
        motor: include the ``motor_current`` auxiliary column (A, on/off segments with ramps).
        pause_fraction: share of the time the board lies still.
        rate_rad_s: per-axis standard deviation of the hand's rotation rate, rad/s.
        band_deg: half-width of the ``band`` coverage, degrees.
        metadata: extra ``key: value`` metadata for the track.
    """
    effects = dict(effects or {})
    _check_args(duration_s, effects, mag_bits, coverage, temp_profile, motor, mag_rate_hz,
                imu_rate_hz)
    streams = np.random.SeedSequence(seed).spawn(7)
    r_motion, r_board, r_effects, r_noise, r_bursts, r_aux, r_clock = (
        np.random.default_rng(s) for s in streams)
    duration_s = float(duration_s)

    # Board errors and environment.
    K = sensor.random_soft_iron(field_uT, r_board) if K is None else _check_K(K)
    b = 30.0 * r_board.standard_normal(3) if b is None else np.asarray(b, dtype=float).reshape(3)
    asa = r_board.integers(165, 181, 3)  # fuse-ROM sensitivity adjustment values
    mag_lsb = sensor.MAG_LSB_UT[mag_bits] * ((asa - 128) / 256.0 + 1.0)
    imu = sensor.imu_errors(r_board)
    field_world = sensor.earth_field(field_uT, dip_deg)
    params = _effect_params(effects, r_effects, field_uT, dip_deg, motor)

    # Clocks: regular sampling instants, jittered stamps.
    tau = params.get("time_lag", {}).get("tau", 0.0)
    t_mag, t_mag_sample = _clock(duration_s, mag_rate_hz, r_clock)
    t_mag_sample = t_mag_sample - tau
    t_imu, t_imu_sample = _clock(duration_s, imu_rate_hz, r_clock)

    pauses = _pauses(duration_s, pause_fraction, r_motion)
    motion = hand_motion(-1.0, duration_s + 1.0, r_motion, coverage=coverage,
                         field_dir=field_world / field_uT, dt=min(1e-3, 0.5 / imu_rate_hz),
                         pauses=pauses, rate_rad_s=rate_rad_s, band_deg=band_deg)
    temp_of = _temperature(temp_profile, temp_start_c, temp_delta_c, duration_s)
    current_of = _motor_current(duration_s, r_aux) if motor else (lambda t: np.zeros_like(t))

    # Magnetometer.
    rot_mag, _, _ = motion.at(t_mag_sample)
    x_body = rot_mag.inv().apply(field_world) / field_uT
    R_mis = Rotation.from_rotvec(params.get("mag_accel_misalignment", {}).get("rotation", np.zeros(3)))
    x = R_mis.inv().apply(x_body)
    u = x @ K.T
    temp_mag, current_mag = temp_of(t_mag_sample), current_of(t_mag_sample)
    clean = u + b + sensor.effect_terms(
        u, {"t": t_mag_sample, "temp": temp_mag, "motor_current": current_mag}, params)
    spans, disturbance_world = _bursts(duration_s, outlier_bursts, burst_uT, r_bursts)
    d_mag = R_mis.inv().apply(rot_mag.inv().apply(disturbance_world(t_mag_sample)))
    disturbance = d_mag @ K.T / field_uT
    mag = sensor.quantize(clean + disturbance + noise_uT * r_noise.standard_normal(clean.shape),
                          mag_lsb, sensor.MAG_RANGE_UT)

    # IMU.
    rot_imu, omega, lin_acc = motion.at(t_imu_sample)
    f_body = rot_imu.inv().apply(lin_acc + np.array([0.0, 0.0, sensor.G]))
    _, accel = sensor.accel_readings(f_body, imu, ACCEL_NOISE, r_noise)
    _, gyro = sensor.gyro_readings(omega, imu, GYRO_NOISE, r_noise)
    temp = temp_of(t_imu_sample) + TEMP_NOISE_C * r_noise.standard_normal(len(t_imu))
    temp = np.round(temp / sensor.TEMP_LSB) * sensor.TEMP_LSB
    current = current_of(t_imu_sample) + CURRENT_NOISE_A * r_noise.standard_normal(len(t_imu))

    meta = {"sensor": "mpu9250", "source": f"simulated by {GENERATOR} seed {seed}",
            "simulated": "yes", "seed": str(seed), "generator": GENERATOR, "mag_unit": "uT",
            "mag_rate_hz": f"{mag_rate_hz:g}", "imu_rate_hz": f"{imu_rate_hz:g}"}
    meta.update(metadata or {})
    aux = {"motor_current": current} if motor else {}
    track = assemble_track(t_mag, mag, t_imu, accel, gyro, temp, aux, meta)

    imu = dict(imu, accel_K=sensor.G * imu["accel_S"])
    truth = SimTruth(K=K, b=b, field_uT=float(field_uT), dip_deg=float(dip_deg),
                     field_world=field_world, effects=params, mag_lsb=mag_lsb,
                     noise_uT=float(noise_uT), imu=imu, outlier_spans=spans, seed=int(seed),
                     t_mag=np.round(t_mag, DECIMALS["t"]), t_sample=t_mag_sample, directions=x,
                     directions_body=x_body, up_body=rot_mag.inv().apply([0.0, 0.0, 1.0]),
                     mag_clean=clean, disturbance=disturbance,
                     temp=temp_mag, motor_current=current_mag)
    return SimResult(track, truth)


def _check_args(duration_s, effects, mag_bits, coverage, temp_profile, motor, mag_rate, imu_rate):
    if not duration_s > 0:
        raise InputError(f"simulate: duration_s must be positive, found {duration_s!r}")
    for name in effects:
        if name in CORE_EFFECTS:
            raise InputError(f"simulate: '{name}' is always simulated; pass K and b instead")
        if name not in EFFECT_NAMES:
            raise UnknownEffectError(f"simulate: unknown effect {name!r}; known: "
                                     f"{', '.join(sensor.SIM_EFFECTS)}")
        if name not in SIMULATED_EFFECTS:
            raise InputError(f"simulate: effect '{name}' declares no simulator truth; "
                             f"simulated: {', '.join(SIMULATED_EFFECTS)}")
    for name in effects:  # after the names: an unknown name is reported first
        info = BY_NAME[name]
        if "aux" in info.needs and not motor:
            raise InputError(f"simulate: '{name}' needs motor=True (the motor_current column)")
        limit = info.simulated.limit
        if limit is not None and not abs(float(effects[name])) <= limit:
            raise InputError(f"simulate: {name} must be within ±{limit:g} "
                             f"{info.simulated.limit_unit}, found {effects[name]!r}")
    if mag_bits not in sensor.MAG_LSB_UT:
        raise InputError(f"simulate: mag_bits must be 14 or 16, found {mag_bits!r}")
    if coverage not in COVERAGES:
        raise InputError(f"simulate: coverage must be one of {', '.join(COVERAGES)}, "
                         f"found {coverage!r}")
    if temp_profile not in TEMP_PROFILES:
        raise InputError(f"simulate: temp_profile must be one of {', '.join(TEMP_PROFILES)}, "
                         f"found {temp_profile!r}")
    if not (0 < mag_rate <= 1000 and 0 < imu_rate <= 4000):
        raise InputError(f"simulate: rates out of range (mag {mag_rate} Hz, IMU {imu_rate} Hz)")


def _check_K(K) -> np.ndarray:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or np.any(np.tril(K, -1) != 0) or np.any(np.diag(K) <= 0):
        raise InputError("simulate: K must be 3×3 upper triangular with a positive diagonal "
                         "(streamcal.calibration.canonical_form gives that form)")
    return K


def _effect_params(effects: Mapping, rng: np.random.Generator, field_uT, dip_deg, motor) -> dict:
    """Truth parameters in the calibration-file layout of :mod:`streamcal.model`, from each
    effect's declared ``simulated.params``. One random direction is drawn per simulated vector
    effect in catalog order, switched on or not, so each effect's parameters do not depend on
    which other effects are on."""
    vector = [n for n in SIMULATED_EFFECTS if BY_NAME[n].simulated.draw == "vector"]
    draws = {name: rng.standard_normal(3) for name in vector}
    vec = {name: (np.asarray(effects[name], dtype=float) if np.ndim(effects[name]) else
                  float(effects[name]) * draws[name] / np.linalg.norm(draws[name]))
           for name in effects if name in vector}
    for name, v in vec.items():
        if v.shape != (3,):
            raise InputError(f"simulate: effect '{name}' takes a magnitude or 3 numbers, "
                             f"found {effects[name]!r}")
    env = SimEnvironment(field_uT=float(field_uT), dip_deg=float(dip_deg), T0_C=T0_C, t0_s=T0_S)
    return {name: BY_NAME[name].simulated.params(vec[name] if name in vec else effects[name], env)
            for name in SIMULATED_EFFECTS if name in effects}


def _clock(duration_s: float, rate_hz: float, rng: np.random.Generator):
    """Stamps (rounded as written) and true sampling instants (s) of a regular sensor clock with
    a random phase; the stamps carry a clipped Gaussian jitter so they stay increasing."""
    period = 1.0 / rate_hz
    phase = rng.uniform(3 * JITTER_S, period)
    sample = phase + period * np.arange(int(np.floor((duration_s - phase) * rate_hz)))
    limit = min(3 * JITTER_S, 0.45 * period)  # < period/2: stamps never swap
    jitter = np.clip(JITTER_S * rng.standard_normal(len(sample)), -limit, limit)
    return np.round(sample + jitter, DECIMALS["t"]), sample


def _pauses(duration_s: float, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(P,2) still intervals: one at the start (the board lies on the desk), the rest random."""
    first = [[-1.0, rng.uniform(0.5, 2.0)]]
    n = int(round(fraction * duration_s / 3.0))
    starts = rng.uniform(0, duration_s, n)
    others = np.stack([starts, starts + rng.uniform(1.5, 4.0, n)], axis=1)
    return np.concatenate([np.array(first), others])


def _temperature(profile: str, start: float, delta: float, duration: float):
    """T(t) in °C for the named profile."""
    if profile == "constant":
        return lambda t: np.full_like(t, start)
    if profile == "warmup":
        return lambda t: start + delta * (1 - np.exp(-np.maximum(t, 0) / (duration / 4)))
    if profile == "ramp":
        return lambda t: start + delta * np.clip(t / duration, 0, 1)
    return lambda t: start + delta * np.sin(np.pi * np.clip(t / duration, 0, 1))


def _motor_current(duration_s: float, rng: np.random.Generator):
    """I(t) in A: alternating off (4–12 s) and on (3–10 s, 0.5–2 A) segments with 0.4 s ramps."""
    n = int(duration_s / 6.0) + 2
    off, on = rng.uniform(4, 12, n), rng.uniform(3, 10, n)
    level = rng.uniform(0.5, 2.0, n)
    ramp = 0.4
    start = np.cumsum(off + on) - on  # on-segment starts
    knots_t = np.stack([start, start + ramp, start + on - ramp, start + on], axis=1).ravel()
    knots_i = np.stack([0 * level, level, level, 0 * level], axis=1).ravel()
    return lambda t: np.interp(t, knots_t, knots_i, left=0.0, right=0.0)


def _bursts(duration_s: float, n: int, peak_uT: float, rng: np.random.Generator):
    """Spans (n,2) s and a function t (M,) → (M,3) world-frame disturbing field, µT.

    Each burst is a dipole (a phone or magnet) moving past in a straight line: its 1/r³ field
    rises and falls within the span (≈ 1 % of the peak at the edges); a cosine taper on the
    outer 15 % makes it exactly zero outside the span. Peaks are scaled to ``peak_uT``."""
    if n == 0:
        return np.empty((0, 2)), lambda t: np.zeros((len(t), 3))
    durations = rng.uniform(2.0, 5.0, n)
    lo, hi, gap = 0.1 * duration_s, 0.95 * duration_s, 1.0
    free = hi - lo - durations.sum() - gap * (n - 1)
    if free <= 0:
        raise InputError(f"simulate: {n} outlier bursts do not fit in {duration_s} s")
    starts = lo + np.sort(rng.uniform(0, free, n)) + np.concatenate(
        [[0.0], np.cumsum(durations[:-1] + gap)])
    spans = np.stack([starts, starts + durations], axis=1)
    moment = _unit(rng.standard_normal((n, 3)))
    normal = _unit(rng.standard_normal((n, 3)))  # closest-approach direction
    velocity = _unit(np.cross(normal, rng.standard_normal((n, 3))))  # ⊥ normal

    def one(k: int, t: np.ndarray) -> np.ndarray:
        mid, half = spans[k].mean(), 0.5 * durations[k]
        pos = normal[k] + ((t - mid) / (half / 4.6))[:, None] * velocity[k]
        r = np.linalg.norm(pos, axis=1, keepdims=True)
        rhat = pos / r
        b = (3 * (rhat @ moment[k])[:, None] * rhat - moment[k]) / r ** 3
        edge = np.clip((half - np.abs(t - mid)) / (0.15 * half), 0, 1)
        return b * (0.5 - 0.5 * np.cos(np.pi * edge))[:, None]

    peaks = [np.linalg.norm(one(k, np.linspace(*spans[k], 4001)), axis=1).max() for k in range(n)]
    gain = peak_uT / np.array(peaks)

    def field(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        out = np.zeros((len(t), 3))
        for k in range(n):  # loop over bursts, vectorized over samples
            inside = (t >= spans[k, 0]) & (t <= spans[k, 1])
            out[inside] = gain[k] * one(k, t[inside])
        return out

    return spans, field


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def assemble_track(t_mag, mag, t_imu, accel, gyro, temp, aux: dict, metadata: dict):
    """Merge mag rows and IMU rows by stamp into one track (NaN = not sampled)."""
    n_mag, n_imu = len(t_mag), len(t_imu)
    t = np.concatenate([t_mag, t_imu])
    order = np.argsort(t, kind="stable")
    is_mag = np.concatenate([np.ones(n_mag, bool), np.zeros(n_imu, bool)])[order]

    def spread(values: np.ndarray, from_mag: bool) -> np.ndarray:
        full = np.full((n_mag + n_imu,) + values.shape[1:], np.nan)
        full[is_mag if from_mag else ~is_mag] = values
        return full

    mag_r = np.round(mag, DECIMALS["mx"])
    cols = dict(
        t=np.round(t[order], DECIMALS["t"]), mag=spread(mag_r, True),
        accel=spread(np.round(accel, DECIMALS["ax"]), False),
        gyro=spread(np.round(gyro, DECIMALS["gx"]), False),
        temp=spread(np.round(temp, DECIMALS["temp"]), False),
        aux={k: spread(np.round(v, DECIMALS.get(k, 4)), False) for k, v in aux.items()})
    return Track.from_arrays(**cols, metadata=metadata)
