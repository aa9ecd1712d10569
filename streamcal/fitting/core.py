"""The free-direction fit of a calibration (every method but the registration effects).

Pure functions on arrays live in the modules of this package (normalization, ellipsoid fits,
kernels, the robust LM, reference methods, the one-pass sphere fit); this entry point validates
the request, picks the data out of a track, runs the method on normalized data and returns a
:class:`~streamcal.calibration.Calibration` in canonical form and sensor units.
"""
from __future__ import annotations

import importlib
from typing import Iterable, Mapping, Sequence

import numpy as np

from ..constants import GRAVITY
from ..calibration import DEFAULT_MODEL, Calibration, canonical_form, field_radius
from ..errors import InputError, InsufficientDataError, UnknownEffectError
from ..inputs.track import Track
from ..model.build import build_effects, check_needs
from ..model.catalog import CORE_EFFECTS, EFFECT_NAMES, REGISTRATION_EFFECTS
from ..units import with_unit
from .outlier_rule import widened_inliers
from .lm import estimation_error, optimal_directions
from .normalize import denormalize_model, normalize
from .observability import assess
from .result import FitResult

#: method name → (module in this package, function), each function maps normalized (N,3)
#: measurements to a normalized (A, b) with m ≈ A x + b.
REFERENCE_METHODS = {
    "magical": ("magical", "fit_magical"),
    "dorveaux": ("dorveaux", "fit_dorveaux"),
    "vasconcelos": ("vasconcelos", "fit_vasconcelos"),
    "kok_schon": ("kok_schon", "fit_kok_schon"),
    "sphere_stream": ("sphere_stream", "fit_sphere_stream"),
}
METHODS = ("autocal", "l1_ellipsoid", "l2_ellipsoid") + tuple(REFERENCE_METHODS)
MIN_SAMPLES = 12
#: Readings whose spread is below this fraction of their size carry no calibration information.
MIN_RELATIVE_SPREAD = 1e-9


def parse_model(model: str | Iterable[str] = DEFAULT_MODEL, add: str | Iterable[str] = ()) -> tuple[str, ...]:
    """Effect names from a comma-separated string or a sequence, plus ``add``; validated."""
    def names(v):
        if isinstance(v, str):
            return [s.strip() for s in v.split(",") if s.strip()]
        return list(v)

    out: list[str] = []
    for name in names(model) + names(add):
        if name not in EFFECT_NAMES:
            raise UnknownEffectError(f"unknown effect {name!r}; the catalog has: {', '.join(EFFECT_NAMES)}")
        if name not in out:
            out.append(name)
    if "scale" in out and "soft_iron" in out:
        out.remove("scale")  # soft_iron contains the per-axis gains
    return tuple(out)


def reference_method(method: str):
    """The fit function of a reference method (``magical``, ``dorveaux``, ``vasconcelos``,
    ``kok_schon``, ``sphere_stream``): ``f(m_n (N,3), **options) -> (A (3,3), b (3,))`` in
    normalized units. Imported on demand so that one method does not import cvxpy for another."""
    module, func = REFERENCE_METHODS[method]
    return getattr(importlib.import_module(f"{__package__}.{module}"), func)


def _measurements(data, sensor: str, covariates):
    """(m (N,3), unit, covariates, track or None) from a Track or an array."""
    if isinstance(data, Track):
        if sensor == "mag":
            m, unit = data.mag, data.mag_unit
            cov = data.covariates_at_mag() if covariates is None else covariates
        else:
            if not data.has("ax"):
                raise InputError(f"{data.path or 'track'}: no accelerometer columns (ax, ay, az) for --sensor accel")
            m, unit = data.accel, data.accel_unit
            cov = covariates or {}
        return np.asarray(m, dtype=float), unit, dict(cov), data
    m = np.asarray(data, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise InputError(f"measurements must be an (N,3) array, got shape {m.shape}")
    if not np.isfinite(m).all():  # the row only when there is one to name (a 10x dearer pass)
        bad = ~np.all(np.isfinite(m), axis=1)
        raise InputError(f"measurements row {int(np.flatnonzero(bad)[0])} is not finite")
    return m, ("uT" if sensor == "mag" else "m/s^2"), dict(covariates or {}), None


def fit_core(data, *, sensor: str = "mag", model: str | Sequence[str] = DEFAULT_MODEL,
        add: str | Sequence[str] = (), kernel: str = "auto", method: str = "autocal",
        tau: float | str | None = None, covariates: Mapping[str, np.ndarray] | None = None,
        check_coverage: bool = True, stage1_max: int = 300, max_iter: int = 300,
        rtol: float = 1e-6, initial: Calibration | None = None, full_output: bool = False):
    """Calibrate a magnetometer (µT) or accelerometer (m/s²) from a Track or an (N,3) array.

    Args:
        data: :class:`streamcal.Track` or (N,3) measurements in the sensor unit.
        sensor: ``"mag"`` or ``"accel"`` (gravity 9.80665 m/s² as the known field).
        model: effect names (docs/effects.md); default ``hard_iron, soft_iron``. ``add``
            appends more.
        kernel: ``auto`` (default: Cauchy, then a Geman–McClure polish), ``cauchy``,
            ``huber``, ``gm``, ``l1`` or ``l2`` (autocal only).
        method: ``autocal`` or a reference method (docs/python_api.md).
        tau: kernel width; None derives it from the data, ``"paper"`` uses √3, a number is
            taken in sensor units.
        covariates: per-sample columns for effects when ``data`` is an array.
        check_coverage: refuse (InsufficientDataError) when the directions seen leave the
            model undetermined.
        initial: warm start (autocal only): skip stage 1 and start the LM from this
            calibration's K and b (its effect parameters are not reused).
        full_output: return a :class:`~streamcal.fitting.result.FitResult` (the calibration
            and the solver's status) instead of the calibration alone.
    Returns: a :class:`Calibration` whose ``inliers``, ``weights`` and ``directions`` cover the
        samples used, in order.
    """
    if sensor not in ("mag", "accel"):
        raise InputError(f"sensor must be 'mag' or 'accel', got {sensor!r}")
    if kernel not in ("auto", "cauchy", "huber", "gm", "l1", "l2"):
        raise InputError(f"unknown kernel {kernel!r}; choose auto, cauchy, huber, gm, l1 or l2")
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    names = parse_model(model, add)
    m, unit, cov, track = _measurements(data, sensor, covariates)
    extra = [n for n in names if n not in CORE_EFFECTS]
    if extra and method != "autocal":
        raise InputError(f"method {method!r} fits only {', '.join(CORE_EFFECTS)}; "
                         f"use method 'autocal' for {', '.join(extra)}")
    if any(n in REGISTRATION_EFFECTS for n in extra):
        raise InputError("registration effects are fitted by streamcal.fitting.fit, not fit_core")
    if len(m) < MIN_SAMPLES:
        raise InsufficientDataError(f"{len(m)} {sensor} samples are too few: at least {MIN_SAMPLES} are needed")
    # per-axis spread over contiguous rows of mᵀ: a third of the cost of the strided axis-0 pass
    spread = float(np.max(np.std(np.ascontiguousarray(m.T), axis=1)))
    if not np.isfinite(spread) or spread <= MIN_RELATIVE_SPREAD * max(1.0, float(np.max(np.abs(m)))) \
            or spread < np.finfo(float).tiny * 1e6:
        raise InsufficientDataError(
            f"the {sensor} readings hardly change (largest per-axis spread "
            f"{with_unit(f'{spread:.3g}', unit)}): "
            "the sensor was not rotated while recording")
    structure = "full" if "soft_iron" in names else "diag" if "scale" in names else "sphere"
    fit_b = "hard_iron" in names
    effects = []
    if extra:
        if track is not None:
            check_needs(extra, track)
        effects = build_effects(extra, cov)

    try:
        t = _sample_times(track, sensor, len(m))
        cal, solver = _fit_checked(m, unit, cov, names, extra, effects, structure, fit_b, t, sensor=sensor,
                            kernel=kernel, method=method, tau=tau, check_coverage=check_coverage,
                            stage1_max=stage1_max, max_iter=max_iter, rtol=rtol, initial=initial)
    except (np.linalg.LinAlgError, FloatingPointError) as exc:
        raise InsufficientDataError(f"the {sensor} readings are numerically degenerate for this "
                                    f"model ({exc}); record while rotating the sensor through many "
                                    "orientations") from None
    if not full_output:
        return cal
    if solver is None:
        return FitResult(cal, None, 0, f"method {method!r} reports no solver status")
    return FitResult(cal, solver.status, solver.iterations, solver.message)


def _sample_times(track, sensor: str, n: int) -> np.ndarray | None:
    """(N,) s times of the samples fitted, in order, or None (an array input, or times out of
    order): what the outlier rule needs to follow a disturbance's ramps."""
    if track is None or sensor != "mag":
        return None
    t = np.asarray(track.t_mag, dtype=float)
    return t if len(t) == n and np.all(np.diff(t) >= 0) else None


def _fit_checked(m, unit, cov, names, extra, effects, structure, fit_b, t, *, sensor, kernel, method,
                 tau, check_coverage, stage1_max, max_iter, rtol, initial) -> Calibration:
    if method == "autocal":
        from .autocal import autocal

        res = autocal(m, kernel=kernel, tau=tau, structure=structure, fit_b=fit_b, effects=effects,
                      covariates=cov, stage1_max=stage1_max, max_iter=max_iter, rtol=rtol,
                      check_coverage=check_coverage,
                      initial=None if initial is None else (initial.K, initial.b))
        K, b, x, inliers, weights = res.K, res.b, res.x, res.inliers, res.weights
        residual_norm = res.residual_norms
        effect_params = {e.name: e.to_physical(t, res.scale) for e, t in zip(effects, res.thetas)}
        seen = x if inliers.all() else x[inliers]  # no copy on clean data
        obs = assess(seen, structure, fit_b, K)
        if not obs.ok:  # the measurements only name the plane in the message
            obs = assess(seen, structure, fit_b, K, m=m[inliers])
        used_kernel = kernel
        sigma, tau_used = res.sigma, res.tau
        solver = res.solver
    else:
        K, b, x, obs = _fit_reference(m, method, structure, max_iter=max_iter, rtol=rtol)
        residual_norm = estimation_error(K, b, m)
        inliers = np.ones(len(m), dtype=bool)
        weights = np.ones(len(m))
        effect_params = {}
        used_kernel = None
        solver = None
        sigma, tau_used = float(np.sqrt(np.mean(residual_norm ** 2) / 3)), None
    if check_coverage and not obs.ok:
        raise InsufficientDataError(obs.message)
    if method == "autocal":   # reported over the one outlier rule (also a disturbance's ramps)
        inliers = widened_inliers(inliers, residual_norm, t)
    kept = residual_norm if inliers.all() else residual_norm[inliers]
    rms = float(np.sqrt(np.mean(kept * kept))) if len(kept) else float("nan")
    field = GRAVITY if sensor == "accel" else (field_radius(K) if unit == "uT" else None)
    extra_keys = {"noise_sigma": sigma}
    if tau_used is not None:
        extra_keys["tau"] = tau_used
    return Calibration(K=K, b=b, sensor=sensor, model=names, effects=effect_params, rms=rms,
                       n=len(m), n_outliers=int((~inliers).sum()), coverage=obs.coverage, unit=unit,
                       field=field, method=method, kernel=used_kernel, inliers=inliers,
                       weights=weights, directions=x, extra=extra_keys), solver


def _fit_reference(m, method, structure, *, max_iter=300, rtol=1e-6):
    from .ellipsoid import ellipsoid_to_model, fit_l1_ellipsoid, fit_l2_ellipsoid

    m_n, center, scale = normalize(m)
    if method in ("l1_ellipsoid", "l2_ellipsoid"):
        solver = fit_l1_ellipsoid if method == "l1_ellipsoid" else fit_l2_ellipsoid
        A, b_n = ellipsoid_to_model(*solver(m_n))
    else:
        kwargs = {} if method == "sphere_stream" else {"max_iter": max_iter, "rtol": rtol}
        A, b_n = reference_method(method)(m_n, **kwargs)
    A = np.asarray(A, dtype=float)
    if not np.all(np.isfinite(A)) or abs(np.linalg.det(A)) < 1e-12:
        raise InsufficientDataError(f"method {method!r} did not produce an invertible sensor matrix")
    K_n, _ = canonical_form(A)
    K, b = denormalize_model(K_n, b_n, center, scale)
    x = optimal_directions(K, b, m)
    return K, b, x, assess(x, structure, True, K, m=m)

