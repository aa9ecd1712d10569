"""MPU-9250 sensor models: the magnetometer with the docs/effects.md effects, accelerometer, gyro.

Magnetometer model (docs/calibration_file.md, the effect terms as in :mod:`streamcal.model`)::

    u = K x                                        undistorted reading, µT
    m = u + b + Σ_e f_e(u, covariates) + K d / F + ε,   then quantized

``x`` the unit field direction in the magnetometer frame, ``K`` upper triangular (µT, it includes
the field strength ``F``), ``b`` the hard iron (µT), ``d`` a disturbing field (µT, the outlier
bursts: a real field, so it goes through the sensor gain), ``ε`` white noise. A general sensor
matrix ``S = K Q`` (soft iron, scale, non-orthogonality) has a rotation ``Q`` that no magnetometer
fit can tell from a frame misalignment, so the simulator draws ``K`` upper triangular and puts
every rotation into ``mag_accel_misalignment``.

Effects: what the user passes to ``simulate(effects={name: magnitude})`` — for 3-vector
parameters the Euclidean norm of a random direction, or the (3,) vector itself — and the field it
adds are declared with each effect (``simulated`` of its
:class:`~streamcal.model.declaration.EffectDeclaration`, in ``streamcal/model/effects/``; its
``magnitude`` says what the number means). ``mag_accel_misalignment`` rotates the true
directions (``x = Rᵀ x_body``, R: mag → accel) and ``time_lag`` samples the magnetometer at
``t − τ`` but stamps it ``t`` (:mod:`.scenario`).

Quantization and ranges are the MPU-9250's (``/work/shared/HARDWARE.md`` §3–§5): AK8963 16-bit
4912/32760 µT/LSB, 14-bit 4912/8190 µT/LSB, ±4912 µT, times the fuse-ROM sensitivity
adjustment ``(ASA − 128)/256 + 1`` that the driver applies; accel ±2 g at 16384 LSB/g; gyro
±250 °/s at 131 LSB/(°/s); temperature 333.87 LSB/°C.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import GRAVITY
from ..model.catalog import BY_NAME, SIMULATED_EFFECTS

G = GRAVITY  # standard gravity, m/s²
MAG_RANGE_UT = 4912.0
MAG_LSB_UT = {16: 4912.0 / 32760.0, 14: 4912.0 / 8190.0}
ACCEL_LSB = G / 16384.0           # m/s² per LSB at ±2 g
ACCEL_RANGE = 2.0 * G
GYRO_LSB = np.radians(1.0 / 131.0)  # rad/s per LSB at ±250 °/s
GYRO_RANGE = np.radians(250.0)
TEMP_LSB = 1.0 / 333.87           # °C per LSB

#: Effects the simulator injects, in catalog order (a view of the declarations).
SIM_EFFECTS = SIMULATED_EFFECTS


def earth_field(strength_uT: float, dip_deg: float) -> np.ndarray:
    """(3,) Earth field in the ENU world frame, µT: pointing north and ``dip_deg`` below the
    horizon (positive dip: northern hemisphere)."""
    dip = np.radians(dip_deg)
    return strength_uT * np.array([0.0, np.cos(dip), -np.sin(dip)])


def quantize(values: np.ndarray, lsb, full_range: float) -> np.ndarray:
    """Round to multiples of ``lsb`` (scalar or per-axis (3,)) and clip to ±``full_range``."""
    lsb = np.asarray(lsb, dtype=float)
    limit = np.floor(full_range / lsb) * lsb
    return np.clip(np.round(values / lsb) * lsb, -limit, limit)


def random_soft_iron(field_uT: float, rng: np.random.Generator, scale_sd: float = 0.05,
                     cross_sd: float = 0.03) -> np.ndarray:
    """(3,3) upper-triangular ``K`` in µT: per-axis gains ``1 + N(0, scale_sd)``, soft iron and
    non-orthogonality ``N(0, cross_sd)`` above the diagonal, times the field strength."""
    K = np.diag(1.0 + scale_sd * rng.standard_normal(3))
    K[np.triu_indices(3, 1)] = cross_sd * rng.standard_normal(3)
    return field_uT * K


def effect_terms(u: np.ndarray, cov: Mapping[str, np.ndarray], params: dict) -> np.ndarray:
    """(N,3) sum of the added effect fields (µT) at the magnetometer instants, in catalog order.

    ``u`` (N,3) undistorted readings ``K x``; ``cov`` the true (N,) columns at those instants
    (``t`` s, ``temp`` °C, ``motor_current`` A); ``params`` the truth parameters
    (``SimTruth.effects`` layout). Each effect adds its declared simulator field; a term effect
    that declares none adds its model term; registration effects add none (the scenario
    applies them to the motion and the clock)."""
    out = np.zeros_like(u)
    for name in SIMULATED_EFFECTS:
        if name not in params:
            continue
        info = BY_NAME[name]
        if info.simulated.field is not None:
            out += info.simulated.field(u, cov, params[name])
        elif info.kind == "term":
            term = info.term.from_params(params[name])
            out += term.term(term.from_physical(params[name], 1.0), u, cov)
    return out


def imu_errors(rng: np.random.Generator) -> dict:
    """Random accelerometer and gyro errors of one board.

    Returns ``accel_S`` (3,3) upper-triangular gain (≈ I), ``accel_b`` (3,) m/s², ``gyro_S``
    (3,) per-axis gains, ``gyro_b`` (3,) rad/s."""
    S = np.diag(1.0 + 0.01 * rng.standard_normal(3))
    S[np.triu_indices(3, 1)] = 0.005 * rng.standard_normal(3)
    return {"accel_S": S, "accel_b": 0.15 * rng.standard_normal(3),
            "gyro_S": 1.0 + 0.01 * rng.standard_normal(3),
            "gyro_b": np.radians(0.5) * rng.standard_normal(3)}


def accel_readings(specific_force: np.ndarray, errors: dict, noise: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Accelerometer (clean, measured) from the body-frame specific force (N,3) m/s²: gain,
    offset, white noise ``noise`` m/s² per axis, ±2 g quantization."""
    clean = specific_force @ errors["accel_S"].T + errors["accel_b"]
    noisy = clean + noise * rng.standard_normal(clean.shape)
    return clean, quantize(noisy, ACCEL_LSB, ACCEL_RANGE)


def gyro_readings(omega: np.ndarray, errors: dict, noise: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Gyro (clean, measured) from the body rate (N,3) rad/s: gain, bias, white noise ``noise``
    rad/s per axis, ±250 °/s quantization."""
    clean = omega * errors["gyro_S"] + errors["gyro_b"]
    noisy = clean + noise * rng.standard_normal(clean.shape)
    return clean, quantize(noisy, GYRO_LSB, GYRO_RANGE)
