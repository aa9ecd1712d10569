"""The partition-based quantile/median helpers give numpy's numbers bit for bit (signed zeros
included), and spread_subset / normalize built on them pick the same samples as before."""
import numpy as np
import pytest

from streamcal.fitting.order_stats import column_medians, median, quantile, quantiles, sorted_median


def _same(a, b) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return bool(np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b)))


def _samples(rng, count):
    for t in range(count):
        n = int(rng.integers(1, 3000))
        a = rng.standard_normal(n) * rng.uniform(1e-3, 100)
        if t % 3 == 0:
            a = np.round(a, 0)                        # ties, and -0.0 beside 0.0
        if t % 4 == 0:
            a = np.abs(a)
        if t % 7 == 0:
            a[: n // 2] = -0.0
        yield a


def test_quantiles_and_median_match_numpy_bit_for_bit():
    rng = np.random.default_rng(3)
    for a in _samples(rng, 1500):
        qs = (0.25, 0.5, float(rng.uniform()))
        assert _same(quantiles(a, qs), np.quantile(a, qs))
        assert _same(quantile(a, qs[2]), np.quantile(a, qs[2]))
        assert _same(median(a), np.median(a))


def test_non_finite_and_empty_fall_back_to_numpy():
    a = np.array([1.0, np.nan, 3.0])
    assert np.isnan(quantile(a, 0.5)) and np.isnan(median(a))
    with pytest.warns(RuntimeWarning):
        assert np.isnan(median(np.array([])))


def test_column_medians_match_numpy():
    rng = np.random.default_rng(4)
    for t in range(300):
        m = np.round(rng.standard_normal((int(rng.integers(1, 2000)), 3)) * (1 + t % 5), t % 2)
        assert _same(column_medians(m), np.median(m, axis=0))


def test_sorted_median_of_every_prefix_matches_numpy():
    rng = np.random.default_rng(5)
    for t in range(100):
        ordered = np.sort(np.round(rng.standard_normal(int(rng.integers(1, 300))), t % 3))
        for k in range(1, len(ordered) + 1):
            assert _same(sorted_median(ordered, k), np.median(ordered[:k]))
