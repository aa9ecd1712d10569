"""Residual families of a fitted model, and how each is distributed.

- ``sensor``: the sensor estimation error of the autocalibration paper, eq. 41,
  ``r_j = g(x̂_j) − m_j`` with ``g(x) = K x + b + Σ_e f_e(θ_e, K x, c_j)`` and ``x̂_j`` re-optimised
  on the unit sphere (the closest point of the fitted surface), sensor unit. Its rms over inliers
  is the ``rms`` of the diagnosis, computed the same way for every model.
- ``magnitude``: ``(‖x‖ − 1)·R`` with ``x`` the calibrated (not renormalised) direction and ``R``
  the field scale (``field`` or the geometric mean of diag K), sensor unit.
- ``dip`` (needs accel): angle between the calibrated field and the accelerometer's "up"
  direction, minus its median, degrees.
- ``gyro`` (needs gyro): the gyro-consistency residual of :mod:`streamcal.fitting.gyro_lag`,
  ``r_ab = K (x̂_b − x_b)`` with ``x̂_b`` sample a's direction carried over the horizon H to
  sample b by the integrated gyro (a fixed world vector seen from a body rotating at ω moves as
  ẋ = −ω × x), the gyro's frame, gains and bias fitted, read at ``t − τ`` with the model's lag τ
  (0 without ``time_lag``); sensor unit, stored at sample a. Its entry also gives ``horizon_s``,
  ``lag_s`` and ``lag_estimate_s`` (τ fitted on this residual alone). It includes the noise of
  two samples (≈ 2σ), so it is compared with itself, not with the noise floor.
  (The consecutive-sample form ‖x̂_{j+1} − x̂_j + ω × x̂ Δt‖ / Δt, :func:`gyro_error`, is all noise
  at 100 Hz and is no longer reported.)
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..model import terms_from_params

GN_ITERATIONS = 6


def _tangent_basis(x: np.ndarray) -> np.ndarray:
    """(N,3,2) orthonormal basis of the plane ⟂ x (N,3) unit vectors."""
    helper = np.where(np.abs(x[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(x, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(x, e1)], axis=2)


def _model(cal, terms, x, cov):
    """g(x) (N,3) and ∂g/∂x: (3,3) when no term depends on u (the same for every sample),
    else (N,3,3)."""
    u = x @ cal.K.T
    g = u + cal.b + sum((t.term(th, u, cov) for t, th in terms), np.zeros_like(u))
    jac = None
    for t, th in terms:
        ju = t.jac_u(th, u, cov)
        if ju is not None:
            jac = (np.broadcast_to(np.eye(3), (len(x), 3, 3)) if jac is None else jac) + ju
    return g, (cal.K if jac is None else jac @ cal.K)


def _times(J: np.ndarray, v: np.ndarray) -> np.ndarray:
    """J v per sample (N,3) for J (3,3) or (N,3,3) and v (N,3)."""
    return v @ J.T if J.ndim == 2 else np.matmul(J, v[:, :, None])[:, :, 0]


def sensor_residual(cal, m: np.ndarray, cov: Mapping[str, np.ndarray]):
    """Eq. 41 residual. Returns ``r`` (N,3) = g(x̂) − m, ``x̂`` (N,3), the signed distance
    ``s`` (N,) of the reading along the outward surface normal (sensor unit) and that unit normal
    (N,3)."""
    x = cal.apply(m, cov)
    r, x, s, normal, _ = closest_point(cal, terms_from_params(cal.effects), m, cov, x)
    return r, x, s, normal


def closest_point(cal, terms, m: np.ndarray, cov: Mapping[str, np.ndarray], x: np.ndarray,
                  iters: int = GN_ITERATIONS):
    """Closest point of the model surface ``g(x) = K x + b + Σ terms`` (``cal``: K, b; ``terms``:
    [(effect term, θ)] in sensor units) to each reading ``m`` (N,3), by ``iters`` Gauss–Newton
    steps on the unit sphere from the directions ``x`` (N,3). Returns ``r`` (N,3) = g(x̂) − m,
    ``x̂`` (N,3), the signed distance ``s`` (N,) along the outward unit normal, that normal
    (N,3) and ∂g/∂x at x̂: (3,3) when no term depends on u (the same for every sample, not
    expanded), else (N,3,3).

    The 2×2 normal equations in the tangent plane are written out per component (no batched
    matmul or einsum over tiny matrices: issue #13 item 2, whole-recording spans)."""
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    for _ in range(iters):
        g, J = _model(cal, terms, x, cov)
        B = _tangent_basis(x)
        e1, e2 = B[:, :, 0], B[:, :, 1]
        j1, j2 = _times(J, e1), _times(J, e2)                  # the columns of J B (N,3)
        d = g - m
        a11, a12, a22 = (j1 * j1).sum(1), (j1 * j2).sum(1), (j2 * j2).sum(1)
        r1, r2 = (j1 * d).sum(1), (j2 * d).sum(1)
        det = a11 * a22 - a12 * a12
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        z1, z2 = (a22 * r1 - a12 * r2) / det, (a11 * r2 - a12 * r1) / det
        x = x - (e1 * z1[:, None] + e2 * z2[:, None])
        x /= np.linalg.norm(x, axis=1, keepdims=True)
    g, J = _model(cal, terms, x, cov)
    if J.ndim == 2:
        normal = np.linalg.solve(J.T, x.T).T
    else:
        normal = np.linalg.solve(np.swapaxes(J, 1, 2), x[..., None])[..., 0]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    r = g - m
    return r, x, -np.einsum("ni,ni->n", r, normal), normal, J


def rms(r: np.ndarray, mask: np.ndarray | None = None) -> float:
    """sqrt(mean ‖r_j‖²) over ``mask`` (sensor unit)."""
    r = r if mask is None else r[mask]
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def magnitude_error(cal, m, cov) -> np.ndarray:
    scale = cal.field or cal.radius
    return (np.linalg.norm(cal.apply(m, cov), axis=1) - 1.0) * scale


def dip_error(x: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Degrees; ``accel`` (N,3) specific force (points up when still)."""
    norm = np.linalg.norm(accel, axis=1, keepdims=True)
    up = accel / np.where(norm > 0, norm, np.nan)  # a zero reading (no accel sample) has no "up"
    ang = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", x, up), -1, 1)))
    return ang - np.nanmedian(ang)


def gyro_error(x: np.ndarray, gyro: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Degrees per second, one value per consecutive pair (N−1,)."""
    dt = np.diff(t)
    w = 0.5 * (gyro[1:] + gyro[:-1])
    xm = x[1:] + x[:-1]
    xm /= np.linalg.norm(xm, axis=1, keepdims=True)
    e = x[1:] - x[:-1] + np.cross(w, xm) * dt[:, None]
    return np.degrees(np.linalg.norm(e, axis=1) / np.where(dt > 0, dt, np.nan))


def binned(values: np.ndarray, by: np.ndarray, bins: int = 12) -> dict:
    """rms of ``values`` (N,) in ``bins`` equal-count bins of ``by`` (N,): edges, rms, n."""
    ok = np.isfinite(values) & np.isfinite(by)
    v, b = values[ok], by[ok]
    if v.size < bins:
        return {"edges": [], "rms": [], "n": []}
    edges = np.unique(np.quantile(b, np.linspace(0, 1, bins + 1)))
    if edges.size < 2:  # a constant covariate (e.g. a log without temperature): one bin
        return {"edges": [float(edges[0])] * 2, "rms": [float(np.sqrt(np.mean(v * v)))],
                "n": [int(v.size)]}
    idx = np.clip(np.searchsorted(edges, b, side="right") - 1, 0, len(edges) - 2)
    n = np.bincount(idx, minlength=len(edges) - 1)
    ss = np.bincount(idx, weights=v * v, minlength=len(edges) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(ss / n)
    return {"edges": [float(e) for e in edges], "rms": [None if not np.isfinite(q) else float(q) for q in r],
            "n": [int(k) for k in n]}


def binned_sphere(values: np.ndarray, x: np.ndarray, n_az: int = 8, n_el: int = 4) -> dict:
    """rms of ``values`` over an azimuth × elevation grid of directions ``x`` (N,3);
    elevation bins are equal-area (uniform in z)."""
    az = np.arctan2(x[:, 1], x[:, 0])
    ia = np.clip(((az + np.pi) / (2 * np.pi) * n_az).astype(int), 0, n_az - 1)
    ie = np.clip(((x[:, 2] + 1) / 2 * n_el).astype(int), 0, n_el - 1)
    idx = ie * n_az + ia
    n = np.bincount(idx, minlength=n_az * n_el)
    ss = np.bincount(idx, weights=values * values, minlength=n_az * n_el)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(ss / n)
    return {"n_azimuth": n_az, "n_elevation": n_el,
            "rms": [[None if not np.isfinite(q) else float(q) for q in row] for row in r.reshape(n_el, n_az)],
            "n": n.reshape(n_el, n_az).tolist()}


def families(cal, m, cov, inliers, r=None, x=None, gyro=None) -> dict:
    """Every residual family available for the data: rms (over inliers) and its distribution
    over time, temperature, aux channels and the sphere of directions. ``gyro``: a gyro-tied
    fit (:class:`streamcal.fitting.registration.RegistrationFit` from
    :func:`streamcal.fitting.gyro_lag.gyro_lag_fit`) for the ``gyro`` family, with optional
    attribute ``lag_estimate`` (s); None leaves the family out."""
    if r is None:
        r, x, _, _ = sensor_residual(cal, m, cov)
    per = {"sensor": (np.linalg.norm(r, axis=1), x),
           "magnitude": (magnitude_error(cal, m, cov), x)}
    if all(k in cov for k in ("ax", "ay", "az")):
        per["dip"] = (dip_error(x, np.stack([cov["ax"], cov["ay"], cov["az"]], axis=1)), x)
    masks = {}
    if gyro is not None:
        per["gyro"] = (np.linalg.norm(gyro.residuals, axis=1), x)
        masks["gyro"] = np.asarray(gyro.inliers, bool)
    from ..model._common import aux_names

    out = {}
    for name, (v, dirs) in per.items():
        sel = masks.get(name, inliers) & np.isfinite(v)
        entry = {"rms": float(np.sqrt(np.mean(v[sel] ** 2))) if sel.any() else None,
                 "unit": {"dip": "deg"}.get(name, "sensor"), "by": {}}
        if name == "gyro":
            extra = gyro.calibration.extra.get("gyro_tied", {})
            estimate = getattr(gyro, "lag_estimate", None)
            entry.update(horizon_s=extra.get("horizon_s"), lag_s=float(gyro.lag),
                         lag_estimate_s=None if estimate is None else float(estimate),
                         n=int(sel.sum()))
        for key in ["t", "temp", *aux_names(cov)]:
            if key in cov:
                entry["by"][key] = binned(v[sel], np.asarray(cov[key], float)[sel])
        entry["by"]["direction"] = binned_sphere(v[sel], dirs[sel])
        out[name] = entry
    return out
