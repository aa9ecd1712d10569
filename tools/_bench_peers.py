"""The calibrators a user would pick from PyPI, beside ``streamcal.fit`` on the same rows.

Context for ``bench_fit_speed.py`` item 5 (not a target). The peers are optional: install them
with ``pip install magcal circuitpython-mag-cal magyc`` (the ``peers`` extra in pyproject.toml);
each one that does not import, or whose fit on the clean rows raises, is skipped with the reason
printed. magyc is not in the extra: magyc 1.0.0 and its navlib declare numpy < 2 and pip
downgrades numpy to install them; restore it afterwards (``pip install "numpy>=2"``) — its
ellipsoid fits run on numpy 2.

The call timed per calibrator is the one its own code or README uses for a hard + soft iron fit
from an (N,3) array:

- ``magcal``: ``MagnetometerCalibrator().ellipsoid_fit(m)`` (``magcal.core``; ``calibrate()``
  wraps it with prints and a per-sample quality loop) → ``center`` and ``transform_matrix``,
  calibrated = T (m − center). Its center is the data mean, not the ellipsoid's centre.
- ``circuitpython-mag-cal``: ``mag_cal.Sensor("+X+Y+Z").fit_ellipsoid(m)`` (the algebraic
  9-term least squares; it also computes its accuracy figure) → ``centre``, ``transform``,
  calibrated = (m − centre) @ transform.
- ``magyc``: ``magyc.benchmark_methods.ellipsoid_fit`` and ``ellipsoid_fit_fang`` (the two
  magnetometer-only ellipsoid fits; its other methods need gyro rates, attitude or a reference
  field) → ``hard_iron``, ``soft_iron``, calibrated = soft_iron⁻¹ (m − hard_iron) as its own
  code applies it.
- textbook algebraic L2: the right singular vector of the raw (N,10) design matrix (an SVD),
  then ``ellipsoid_to_model`` → (K, b), calibrated = K⁻¹ (m − b) — a usable calibration, where
  the ``fit_l2_ellipsoid`` baseline stops at the conic's coefficients. The SVD goes through
  OpenBLAS's threads: with the second core busy it took 16 ms instead of 0.14 ms on the 2-core
  bench machine (``OPENBLAS_NUM_THREADS=1`` keeps it at 0.14 ms), so read its rounds.
- ``streamcal.fit(m)`` (default): (K, b), calibrated = K⁻¹ (m − b).

One convention for all: each result becomes the correction map W and offset b with
calibrated = W (m − b). Any rotation of W gives the same magnitudes and the peers scale their
output to arbitrary radii, so W is compared through what it fixes: Q = Wᵀ W, written as the
canonical upper-triangular sensor matrix K (K⁻ᵀ K⁻¹ = Q, streamcal's form) and normalized to
K̂ = K / |det K|^⅓. The deviation (paper eq. 40 on [R K̂, b]) is
``‖[K̂ − K̂₀, (b − b₀)/R]‖_F / ‖[K̂₀, b₀/R]‖_F`` between a calibrator's fit on the clean rows (₀)
and its fit on the same rows with 10 % gross outliers appended (10 % of all rows, drawn
uniformly in the data's bounding box widened to ±2× its half-range about its centre, fixed
seed); R is ``streamcal.fit``'s field radius on the clean rows, the same for every calibrator.
The overall gain is left out (it is the field's magnitude, not a calibration error). The spread
column is std/mean of ‖W (m − b)‖ over the clean rows with the clean fit: how round each one's
calibrated field is. A fit that raises on the outlier rows, or returns a non-finite or singular
map, is shown as a breakdown with its reason.
"""
from __future__ import annotations

import numpy as np

OUTLIER_FRACTION = 0.10
OUTLIER_WIDTH = 2.0  # × the data's half-range about its bounding-box centre


def with_outliers(m: np.ndarray, seed: int = 0) -> np.ndarray:
    """``m`` (N,3) with gross outliers appended so that they are OUTLIER_FRACTION of all rows."""
    rng = np.random.default_rng(seed)
    lo, hi = m.min(axis=0), m.max(axis=0)
    c, h = (lo + hi) / 2, OUTLIER_WIDTH * (hi - lo) / 2
    k = int(round(OUTLIER_FRACTION * len(m) / (1 - OUTLIER_FRACTION)))
    return np.vstack([m, rng.uniform(c - h, c + h, (k, 3))])


def _streamcal():
    from streamcal.fitting import fit

    return fit, lambda cal: (np.linalg.inv(cal.K), cal.b)


def _textbook():
    from streamcal.fitting.ellipsoid import design_matrix, ellipsoid_to_model, unpack

    def call(m):
        C, d, e = unpack(np.linalg.svd(design_matrix(m), full_matrices=False)[2][-1])
        sign = 1.0 if np.trace(C) > 0 else -1.0  # the singular vector's sign is arbitrary
        return ellipsoid_to_model(sign * C, sign * d, sign * e)

    return call, lambda kb: (np.linalg.inv(kb[0]), kb[1])


def _magcal():
    from magcal.core import MagnetometerCalibrator

    calibrator = MagnetometerCalibrator()
    return calibrator.ellipsoid_fit, lambda p: (p["transform_matrix"], p["center"])


def _mag_cal():
    from mag_cal import Sensor

    def call(m):
        sensor = Sensor("+X+Y+Z")
        sensor.fit_ellipsoid(m)
        return sensor

    return call, lambda s: (s.transform.T, s.centre)  # (m − c) @ T = Tᵀ (m − c)


def _magyc(name):
    def load():
        from magyc.benchmark_methods import ellipsoidfit

        return getattr(ellipsoidfit, name), lambda r: (np.linalg.inv(r[1]), r[0])
    return load


#: (label, loader): loader() → (call(m), to_wb(result) → (W, b)); raises if unavailable.
CALIBRATORS = (
    ("streamcal.fit (default)", _streamcal),
    ("textbook algebraic L2 (SVD + ellipsoid_to_model)", _textbook),
    ("magcal: MagnetometerCalibrator().ellipsoid_fit", _magcal),
    ("circuitpython-mag-cal: Sensor().fit_ellipsoid", _mag_cal),
    ("magyc: ellipsoid_fit", _magyc("ellipsoid_fit")),
    ("magyc: ellipsoid_fit_fang", _magyc("ellipsoid_fit_fang")),
)


def shape_offset(W: np.ndarray, b: np.ndarray):
    """(K̂ (3,3) upper triangular with det 1, b (3,)) from calibrated = W (m − b)."""
    L = np.linalg.cholesky(W.T @ W)
    K = np.linalg.inv(L.T)
    return K / np.cbrt(abs(np.linalg.det(K))), np.asarray(b, dtype=float).reshape(3)


def deviation(wb, wb_ref, radius: float) -> float:
    """Eq. 40 on [R K̂, b] of two (W, b) results (module docstring)."""
    (k, b), (k0, b0) = shape_offset(*wb), shape_offset(*wb_ref)
    ref = np.hstack([k0, b0[:, None] / radius])
    return float(np.linalg.norm(np.hstack([k - k0, (b - b0)[:, None] / radius])) / np.linalg.norm(ref))


def spread(wb, m: np.ndarray) -> float:
    """std/mean of the calibrated magnitudes ‖W (m − b)‖ over the rows of ``m``."""
    W, b = wb
    r = np.linalg.norm((m - b) @ W.T, axis=1)
    return float(np.std(r) / np.mean(r))


def peers_table(m: np.ndarray, repeats: int, median_seconds, rounds: int = 2, seed: int = 0) -> None:
    """Time every available calibrator on ``m`` (N,3), alternated with ``streamcal.fit`` over
    ``rounds`` rounds of ``median_seconds(call, repeats)`` each; print the table."""
    dirty = with_outliers(m, seed)
    ready = {}
    for label, load in CALIBRATORS:
        try:
            call, to_wb = load()
            clean = to_wb(call(m))
        except Exception as exc:  # noqa: BLE001 — a peer that fails is skipped, said why
            print(f"  skipped {label}: {type(exc).__name__}: {exc}")
            continue
        try:
            noisy = to_wb(call(dirty))
        except Exception as exc:  # noqa: BLE001 — a breakdown under outliers is a result
            noisy = f"breakdown ({type(exc).__name__}: {str(exc)[:60]})"
        ready[label] = (call, clean, noisy)
    ours = "streamcal.fit (default)"
    if ours not in ready:
        print("  peers table skipped: streamcal.fit failed")
        return
    times = {label: [] for label in ready}
    for _ in range(rounds):
        for label, (call, _, _) in ready.items():
            times[label].append(median_seconds(lambda c=call: c(m), repeats))
    radius = float(np.cbrt(abs(np.linalg.det(np.linalg.inv(ready[ours][1][0])))))
    base = float(np.median(times[ours]))
    print(f"\n#### Peers on the same {len(m)} rows, medians of {repeats}, {rounds} alternated rounds "
          f"(+{len(dirty) - len(m)} outlier rows for the deviation, seed {seed})\n")
    print("| calibrator | ms (rounds) | streamcal.fit ÷ it | clean-fit ‖calibrated‖ spread | "
          "deviation with 10 % outliers (eq. 40, shape + offset) |")
    print("|---|---|---|---|---|")
    for label, (_, clean, noisy) in ready.items():
        sec = float(np.median(times[label]))
        print(f"| {label} | {sec * 1e3:.3f} ({' / '.join(f'{v * 1e3:.3f}' for v in times[label])}) | "
              f"{base / sec:.1f} | {100 * spread(clean, m):.2f} % | "
              f"{_deviation_text(noisy, clean, radius)} |")


def _deviation_text(noisy, clean, radius: float) -> str:
    """The deviation in %, or why there is none: the fit on the outlier rows raised, gave a
    non-finite map, or a singular one."""
    if isinstance(noisy, str):
        return noisy
    if not all(np.all(np.isfinite(a)) for a in noisy):
        return "breakdown (non-finite W or b)"
    try:
        return f"{100 * deviation(noisy, clean, radius):.3f} %"
    except np.linalg.LinAlgError:
        return "breakdown (singular W)"
