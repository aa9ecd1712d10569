"""SphereStats: the one-pass 25-sum Gauss–Newton sphere fit equals the batch fit."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from streamcal.errors import InsufficientDataError
from streamcal.fitting.sphere_stream import SphereStats, fit_sphere_stream


def _sphere_samples(n, center, radius, noise, seed, cap_deg=180.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[np.degrees(np.arccos(d[:, 2])) <= cap_deg]
    return np.asarray(center) + radius * d + rng.normal(scale=noise, size=d.shape)


def _batch_fit(m, start):
    """The same objective, Σ (1 − ‖m − c‖²/R²)², minimised with all samples in memory."""
    res = least_squares(lambda p: 1.0 - ((m - p[:3]) ** 2).sum(axis=1) / p[3] ** 2, start,
                        method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return res.x[:3], res.x[3]


def _kasa(m):
    A = np.hstack([2 * m, np.ones((len(m), 1))])
    sol = np.linalg.lstsq(A, (m ** 2).sum(axis=1), rcond=None)[0]
    return np.concatenate([sol[:3], [np.sqrt(sol[3] + sol[:3] @ sol[:3])]])


@pytest.mark.parametrize("center, radius, noise, cap", [
    ((12.0, -30.0, 45.0), 48.0, 0.5, 180.0),
    ((350.0, -120.0, 800.0), 50.0, 1.0, 180.0),       # offset ≫ radius: cancellation check
    ((0.0, 0.0, 0.0), 9.81, 0.05, 100.0),              # accelerometer-like, partial coverage
    ((3000.0, 1000.0, -2500.0), 330.0, 3.0, 120.0),    # counts
])
def test_equals_batch_least_squares(center, radius, noise, cap):
    m = _sphere_samples(4000, center, radius, noise, seed=3, cap_deg=cap)
    stats = SphereStats()
    for block in np.array_split(m, 13):
        stats.update(block)
    c, R = stats.fit()
    c_ref, R_ref = _batch_fit(m, _kasa(m))
    np.testing.assert_allclose(c, c_ref, rtol=0, atol=1e-6 * radius)
    assert R == pytest.approx(R_ref, rel=1e-8)
    # and the fit is the sphere the samples came from, to within the noise
    np.testing.assert_allclose(c, center, atol=100 * noise / np.sqrt(len(m)))


def test_axes_model_recovers_per_axis_radii():
    rng = np.random.default_rng(5)
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.array([45.0, 50.0, 55.0])
    m = np.array([5.0, -7.0, 9.0]) + radii * d
    stats = SphereStats()
    stats.update(m)
    c, s = stats.fit_axes()
    np.testing.assert_allclose(c, [5.0, -7.0, 9.0], atol=1e-6)
    np.testing.assert_allclose(s, radii, rtol=1e-8)


def test_merge_equals_single_pass_and_skips_nan_rows():
    m = _sphere_samples(3000, (40.0, 10.0, -20.0), 50.0, 0.3, seed=7)
    whole = SphereStats()
    whole.update(m)
    a, b = SphereStats(), SphereStats()
    a.update(m[:500])
    dirty = m[500:].copy()
    dirty[::50] = np.nan
    b.update(m[500:])
    c = SphereStats()
    assert c.update(dirty) == len(dirty) - len(dirty[::50])
    a.merge(b)
    assert a.n == whole.n
    (c1, r1), (c2, r2) = a.fit(), whole.fit()
    np.testing.assert_allclose(c1, c2, atol=1e-9)
    assert r1 == pytest.approx(r2, rel=1e-12)
    assert a.cost(c1, r1) == pytest.approx(whole.cost(c2, r2), rel=1e-6)


def test_memory_is_constant():
    stats = SphereStats()
    stats.update(np.ones((10, 3)))
    sizes = [v.nbytes for v in (stats.s1, stats.s2, stats.s21, stats.s22)]
    stats.update(_sphere_samples(100_000, (0, 0, 0), 50.0, 0.1, seed=1))
    assert [v.nbytes for v in (stats.s1, stats.s2, stats.s21, stats.s22)] == sizes


def test_degenerate_data_raises():
    stats = SphereStats()
    stats.update(np.tile([1.0, 2.0, 3.0], (100, 1)))
    with pytest.raises(InsufficientDataError):
        stats.fit()
    with pytest.raises(InsufficientDataError):
        SphereStats().fit()


def test_fit_sphere_stream_returns_K_b():
    m = _sphere_samples(2000, (1.0, 2.0, 3.0), 40.0, 0.0, seed=2)
    K, b = fit_sphere_stream(m)
    np.testing.assert_allclose(K, 40.0 * np.eye(3), atol=1e-8)
    np.testing.assert_allclose(b, [1.0, 2.0, 3.0], atol=1e-8)
