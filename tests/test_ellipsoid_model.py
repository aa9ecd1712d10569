"""``ellipsoid_to_model`` (Algorithm 1, steps 2–4) written out for 3×3 matches numpy's
Cholesky/solve/inverse on the same quadrics, and refuses the same non-ellipsoids."""
import numpy as np
import pytest

from streamcal.errors import InsufficientDataError
from streamcal.fitting.ellipsoid import ellipsoid_to_model, fit_l2_ellipsoid


def numpy_model(C, d, e):
    """The same steps through numpy.linalg: b = −C⁻¹d, μ = −bᵀd − e, K = √μ chol(C)⁻ᵀ."""
    C = 0.5 * (C + C.T)
    L = np.linalg.cholesky(C)
    b = -np.linalg.solve(C, d)
    mu = float(-b @ d - e)
    return np.triu(np.sqrt(mu) * np.linalg.inv(L.T)), b


def test_random_ellipsoids_symmetric_or_not():
    rng = np.random.default_rng(5)
    for k in range(500):
        A = rng.standard_normal((3, 3))
        C = A @ A.T + 0.1 * np.eye(3)
        if k % 2:                                      # a non-symmetric C: its symmetric part counts
            C = C + np.triu(rng.standard_normal((3, 3)) * 0.05, 1)
        d = rng.standard_normal(3)
        e = float(-(d @ np.linalg.solve(0.5 * (C + C.T), d))) - rng.uniform(0.1, 5.0)
        K, b = ellipsoid_to_model(C, d, e)
        K_ref, b_ref = numpy_model(C, d, e)
        np.testing.assert_allclose(K, K_ref, rtol=1e-9, atol=1e-12 * np.abs(K_ref).max())
        np.testing.assert_allclose(b, b_ref, rtol=1e-9, atol=1e-12 * np.abs(b_ref).max())
        assert np.all(np.tril(K, -1) == 0.0) and np.all(np.diag(K) > 0)


@pytest.mark.parametrize("C", [np.diag([1.0, -1.0, 1.0]), np.diag([1.0, 1.0, 0.0]),
                               np.full((3, 3), np.nan), np.diag([np.inf, 1.0, 1.0])])
def test_not_positive_definite(C):
    with pytest.raises(InsufficientDataError, match="not an ellipsoid"):
        ellipsoid_to_model(C, np.zeros(3), -1.0)


@pytest.mark.parametrize("d,e", [(np.zeros(3), 1.0), (np.array([np.nan, 0, 0]), -1.0),
                                 (np.zeros(3), np.inf)])
def test_empty_or_imaginary(d, e):
    with pytest.raises(InsufficientDataError, match="empty or imaginary"):
        ellipsoid_to_model(np.eye(3), d, e)


def test_the_algebraic_fit_refuses_non_finite_samples():
    m = np.random.default_rng(1).standard_normal((50, 3))
    m[7, 1] = np.nan
    with pytest.raises(InsufficientDataError, match="finite"):
        fit_l2_ellipsoid(m)
