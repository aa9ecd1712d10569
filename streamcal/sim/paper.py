"""The synthetic protocol of the autocalibration paper (Hong, Kang, Kim 2020, §III-B, eqs. 35–38).

    K = σ_K (I + 0.1 [Δk1 Δk2 Δk4; 0 Δk3 Δk5; 0 0 Δk6]),  Δk_i ~ N(0, 1)      (35)
    b = σ_b ([1 1 1]ᵀ + Δb),                            Δb_i ~ N(0, 1)      (36)
    m_j = K x_j + b + ε_j,  x_j uniform on S²,          ε_j ~ N(0, σ² I)    (37)
    m_j ← m_j + ξ_j for a fraction η of the samples,    ξ_ji ~ U(−ζ, ζ)    (38)

The paper uses n = 1000, σ_K = 100, σ_b = 20, ζ = 100, σ ∈ [0, 2], η ∈ [0, 0.5].
"""
from __future__ import annotations

import numpy as np


def paper_protocol(n: int = 1000, sigma: float = 1.0, eta: float = 0.1, seed: int = 0,
                   sigma_K: float = 100.0, sigma_b: float = 20.0, zeta: float = 100.0):
    """One synthetic data set of the paper's protocol.

    Returns ``(m, K, b, inliers)``: readings (n,3), the true upper-triangular K (3,3) and b (3,)
    (in the readings' unit), and a bool (n,) mask, False on exactly ``round(eta·n)`` outliers.
    """
    if n < 1 or sigma < 0 or not 0 <= eta <= 1 or zeta < 0:
        raise ValueError(f"paper_protocol: need n ≥ 1, σ ≥ 0, 0 ≤ η ≤ 1, ζ ≥ 0 "
                         f"(found n={n}, sigma={sigma}, eta={eta}, zeta={zeta})")
    rng = np.random.default_rng(seed)
    dk = np.zeros((3, 3))
    dk[np.triu_indices(3)] = rng.standard_normal(6)
    K = sigma_K * (np.eye(3) + 0.1 * dk)
    b = sigma_b * (1.0 + rng.standard_normal(3))
    x = rng.standard_normal((n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = x @ K.T + b + sigma * rng.standard_normal((n, 3))
    inliers = np.ones(n, dtype=bool)
    inliers[rng.choice(n, size=int(round(eta * n)), replace=False)] = False
    m[~inliers] += rng.uniform(-zeta, zeta, size=(int((~inliers).sum()), 3))
    return m, K, b, inliers
