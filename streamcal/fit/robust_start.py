"""A starting model for heavily contaminated data (beyond what the L1 ellipsoid withstands).

With most samples gross outliers (the paper's protocol at η = 50–70 %), the L1 ellipsoid keeps
the centre roughly right but misjudges the size and shape. Concentration steps — refit the
algebraic ellipsoid to the quarter of samples nearest the current surface, repeat until stable
(the "C-steps" of least-trimmed-squares) — then lock onto the thin shell of inliers, provided the
start has the right size; so we start from several radial scalings of the L1 ellipsoid and keep
the model with the smallest low quantile of radial errors (an LQS criterion, which still works
when the inliers are a minority). Both run on a direction-spread subset, so rest periods (dense
clusters of identical samples) cannot pose as a shell.
"""
from __future__ import annotations

import numpy as np

from ..errors import InsufficientDataError
from .ellipsoid import ellipsoid_to_model, fit_l2_ellipsoid, spread_subset

#: Radial scalings of the starting ellipsoid tried.
SCALES = (0.6, 0.8, 1.0, 1.25, 1.5)
#: Fraction of samples kept by each concentration step, and the quantile scored.
KEEP, SCORE_QUANTILE = 0.25, 0.2


def radial_error(K: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """| ‖K⁻¹(m_j − b)‖ − 1 | per sample (N,): the relative distance from the ellipsoid."""
    return np.abs(np.linalg.norm(np.linalg.solve(K, (m - b).T), axis=0) - 1.0)


def lqs_score(K: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    """The SCORE_QUANTILE quantile of the radial errors (lower is better)."""
    return float(np.quantile(radial_error(K, b, m), SCORE_QUANTILE))


def concentrate(K: np.ndarray, b: np.ndarray, m: np.ndarray, steps: int = 20):
    """C-steps from (K, b) on normalized measurements m (N,3); returns the final (K, b)."""
    for _ in range(steps):
        r = radial_error(K, b, m)
        near = m[r <= np.quantile(r, KEEP)]
        try:
            K_new, b_new = ellipsoid_to_model(*fit_l2_ellipsoid(near[spread_subset(near, 300)]))
        except InsufficientDataError:
            break
        done = np.allclose(K_new, K, rtol=1e-6, atol=1e-9) and np.allclose(b_new, b, atol=1e-9)
        K, b = K_new, b_new
        if done:
            break
    return K, b


def robust_start(K0: np.ndarray, b0: np.ndarray, m: np.ndarray, n_max: int = 2000):
    """Best (K, b) by :func:`lqs_score` over concentration runs from scaled copies of (K0, b0).

    Works on at most ``n_max`` samples spread over directions: a board resting in one pose
    gives a dense cluster that any thin shell through it would "fit" with a tiny score."""
    m = m[spread_subset(m, n_max)]
    best = None
    for scale in SCALES:
        K, b = concentrate(K0 * scale, b0, m)
        score = lqs_score(K, b, m)
        if best is None or score < best[0]:
            best = (score, K, b)
    return best[1], best[2]
