"""Inverting the sensor model: from readings ``m`` back to directions ``x``.

Solve ``m = u + b + Σ_e f_e(θ_e, u, c)`` for ``u`` by Newton's method, all samples at once
(per-sample 3×3 systems solved on stacked arrays), then ``x = K⁻¹ u``. Purely additive effects
need a single step; u-dependent ones (temperature scale, cubic) converge quadratically from
``u₀ = m − b − Σ f(θ, m − b, c)`` since the terms are small perturbations.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
import scipy.linalg

from ..errors import InsufficientDataError, MissingColumnsError
from .build import terms_from_params

MAX_ITER = 50


def invert_model(cal, m: np.ndarray, covariates: Mapping[str, np.ndarray]) -> np.ndarray:
    """Directions (N,3) for readings ``m`` (N,3, sensor unit) under calibration ``cal``,
    ``covariates`` the (N,) columns the effects need (``t``, ``temp``, aux channels)."""
    m = np.asarray(m, dtype=float).reshape(-1, 3)
    n = len(m)
    cov = {}
    for key, value in (covariates or {}).items():
        arr = np.asarray(value, dtype=float).reshape(-1)
        if arr.size == 1 and n != 1:
            arr = np.full(n, arr[0])
        if arr.shape != (n,):
            raise MissingColumnsError(f"covariate '{key}' has {arr.size} values for {n} readings")
        cov[key] = arr
    terms = terms_from_params(cal.effects)
    target = m - cal.b
    u = target.copy()
    if terms:
        u = target - sum(t.term(th, target, cov) for t, th in terms)
        eye = np.eye(3)
        for _ in range(MAX_ITER):
            resid = u + sum(t.term(th, u, cov) for t, th in terms) - target
            jac = eye[None] + sum(j for j in (t.jac_u(th, u, cov) for t, th in terms) if j is not None)
            step = np.linalg.solve(jac, resid[..., None])[..., 0]
            u = u - step
            if not np.any(np.abs(step) > 1e-13 * (1.0 + np.abs(u))):
                break
        else:
            bad = int(np.sum(np.any(np.abs(step) > 1e-8 * (1.0 + np.abs(u)), axis=1)))
            if bad:
                raise InsufficientDataError(f"the model cannot be inverted for {bad} readings "
                                            "(effect terms too large for them)")
    return scipy.linalg.solve_triangular(cal.K, u.T, lower=False).T
