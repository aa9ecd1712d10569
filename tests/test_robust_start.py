"""Stage-1 starts under contamination: the concentration start (uniform gross outliers, up to
η = 70 %) and the coherent-disturbance start (a magnet riding on the board for a while: a second
shell, contiguous in time, seen from more directions than the undisturbed cap).

The simulated disturbance mirrors BROAD trial 32 (RESULTS.md): field 45 µT, noise 0.7 µT,
a hard-iron shift of 55 µT (more than a field radius, so the two shells are far apart over most
of the sphere but do intersect), the undisturbed motion a 60° cap around −z plus rest periods at
the start and the end, the disturbed motion covering three quarters of the sphere.
"""
from __future__ import annotations

import importlib
import itertools
import math

import numpy as np
import pytest

from streamcal.fitting import fit
from streamcal.fitting.autocal import _looks_contaminated, stage1
from streamcal.fitting.ellipsoid import directions_from_model, spread_subset
from streamcal.fitting.normalize import normalize
from streamcal.fitting.shared_shape import shift_start
from streamcal.fitting.robust_start import (MAX_ANISOTROPY, anisotropy, coherent_start,
                                        contiguous_bad_chunks, fit_sphere,
                                        longest_run_probability, lqs_score, radial_error,
                                        robust_start)
from streamcal.sim import paper_protocol

FIELD, NOISE = 45.0, 0.7                       # µT
K_TRUE = FIELD * np.array([[1.0, 0.01, 0.03], [0.0, 0.98, 0.01], [0.0, 0.0, 1.01]])
B_TRUE = np.array([1.5, 0.5, 1.2])             # µT
# µT, the magnet's field in the body frame: across the cap's axis (along it, one elongated
# ellipsoid threads both shells within the noise and nothing looks contaminated)
SHIFT = np.array([55.0, -2.0, -1.0])


def model_error(K, b, K_ref, b_ref) -> float:
    """Paper eq. 40."""
    A, R = np.column_stack([K, b]), np.column_stack([K_ref, b_ref])
    return float(np.linalg.norm(A - R) / np.linalg.norm(R))


def cap(rng, n, half_angle_deg, axis):
    """n unit vectors uniform on the cap of the given half-angle around ``axis`` (3,)."""
    z = rng.uniform(np.cos(np.radians(half_angle_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    v = np.column_stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    if np.allclose(a, [0, 0, 1]):
        return v
    if np.allclose(a, [0, 0, -1]):
        return v * np.array([1, -1, -1])
    raise ValueError("axis must be ±z")


def coherent_track(seed: int = 0, n: int = 6000):
    """(m (n,3) in time order, disturbed (n,) bool): rest, cap, disturbance, cap, rest
    (18 %, 15 %, 35 %, 14 %, 18 %: 65 % undisturbed, of which over half at rest)."""
    rng = np.random.default_rng(seed)
    sizes = np.round(np.array([0.18, 0.15, 0.35, 0.14, 0.18]) * n).astype(int)
    sizes[-1] = n - sizes[:-1].sum()
    rest_dir = np.array([[0.1, 0.3, -0.95]]) / np.linalg.norm([0.1, 0.3, -0.95])
    parts = [np.repeat(rest_dir, sizes[0], axis=0), cap(rng, sizes[1], 60, [0, 0, -1]),
             cap(rng, sizes[2], 120, [0, 0, 1]), cap(rng, sizes[3], 60, [0, 0, -1]),
             np.repeat(rest_dir, sizes[4], axis=0)]
    x = np.vstack(parts)
    disturbed = np.zeros(n, bool)
    disturbed[sizes[:2].sum(): sizes[:3].sum()] = True
    m = x @ K_TRUE.T + B_TRUE + NOISE * rng.standard_normal((n, 3))
    m[disturbed] += SHIFT
    return m, disturbed


def plain_start(m_n):
    """The start autocal had before the coherent search: L1 ellipsoid, then the concentration
    start when the L1 residuals look contaminated."""
    K0, b0 = stage1(m_n)
    x0 = directions_from_model(K0, b0, m_n)
    r0 = np.linalg.norm(x0 @ K0.T + b0 - m_n, axis=1)
    contaminated = _looks_contaminated(r0, radial_error(K0, b0, m_n))
    if contaminated:
        K1, b1 = robust_start(K0, b0, m_n)
        spread = m_n[spread_subset(m_n, 2000)]
        if lqs_score(K1, b1, spread) < lqs_score(K0, b0, spread):
            K0, b0 = K1, b1
    return K0, b0, contaminated


# --- sphere fits -----------------------------------------------------------------------------

def test_sphere_fit_is_exact_on_a_noise_free_cap():
    rng = np.random.default_rng(1)
    c, r = np.array([3.0, -2.0, 7.0]), 4.5
    m = c + r * cap(rng, 200, 40, [0, 0, 1])
    K, b = fit_sphere(m)
    assert np.allclose(b, c, atol=1e-8) and np.allclose(K, r * np.eye(3), atol=1e-8)


# --- the coherent disturbance -----------------------------------------------------------------

# Every seed tried is listed. On seeds 2, 3 and 7 the chunks' inlier fractions under the plain
# start differ by less than robust_start.HETEROGENEITY; the search runs there because the chunks
# that fit badly are contiguous in time (robust_start.contiguous_bad_chunks).


@pytest.mark.parametrize("seed", range(8))
def test_coherent_disturbance_start_lands_on_the_undisturbed_shell(seed):
    m, disturbed = coherent_track(seed)
    m_n, center, scale = normalize(m)
    K0, b0, contaminated = plain_start(m_n)
    assert contaminated
    before = model_error(scale * K0, scale * b0 + center, K_TRUE, B_TRUE)
    choice = coherent_start(K0, b0, m_n)
    assert choice is not None
    K, b = scale * choice.K * np.sign(np.diag(choice.K))[None, :], scale * choice.b + center
    after = model_error(K, b, K_TRUE, B_TRUE)
    # The shifted shell is ‖SHIFT‖/‖[K b]‖ ≈ 70 % away; a start within 10 % is in the basin of
    # the undisturbed fit (on BROAD 32 the same search starts 6.7 % from it).
    assert after < 0.10, (before, after)
    assert after < before / 3
    # the support is the undisturbed time: every chunk wholly inside the disturbance is out,
    # and at most one chunk (≈ 1/24 of the track) on each edge of it is mixed
    chunk = len(m) / 24
    assert choice.support[disturbed].mean() < 2 * chunk / disturbed.sum()
    assert choice.support[~disturbed].mean() > 1 - 2 * chunk / (~disturbed).sum()
    assert choice.score == pytest.approx(choice.support.mean(), abs=0.02)


@pytest.mark.parametrize("seed", range(8))
def test_the_same_samples_in_random_order_do_not_look_coherent(seed):
    # what gives the disturbance away is time: shuffled, its samples are uniform outliers
    m, _ = coherent_track(seed)
    m_n = normalize(m[np.random.default_rng(seed).permutation(len(m))])[0]
    K0, b0, contaminated = plain_start(m_n)
    assert contaminated
    assert coherent_start(K0, b0, m_n) is None


def test_longest_run_probability_matches_enumeration():
    for n, k, run in [(8, 3, 2), (10, 5, 3), (9, 4, 4), (12, 6, 1), (11, 7, 5), (7, 0, 1)]:
        hits = 0
        for ones in itertools.combinations(range(n), k):
            bad = np.zeros(n, bool)
            bad[list(ones)] = True
            edges = np.flatnonzero(np.concatenate([[True], ~bad, [True]]))
            hits += np.diff(edges).max() - 1 >= run
        assert longest_run_probability(n, k, run) == pytest.approx(hits / math.comb(n, k))


def test_contiguity_gate_needs_one_long_run_of_bad_chunks():
    good, bad = np.full(24, 0.95), 0.55
    block = good.copy()
    block[6:16] = bad                          # one run of 10 chunks: spread 0.4 < HETEROGENEITY
    assert contiguous_bad_chunks(block)
    scattered = good.copy()
    scattered[::2][:10] = bad                  # the same chunks scattered in time
    assert not contiguous_bad_chunks(scattered)
    short = good.copy()
    short[-4:] = bad                           # contiguous but short (a tail, as on tiva 08)
    assert not contiguous_bad_chunks(short)
    faint = good.copy()
    faint[6:16] = good[0] - 0.2                # contiguous but within the binomial spread
    assert not contiguous_bad_chunks(faint)


# With the shared-shape refinement (streamcal.fitting.shared_shape: one K, offsets b and b + Δ) the
# whole fit is 0.14–0.31 % from the truth on every seed, while the undisturbed part's own fit
# (a cap plus rests) is 0.6–4.4 % from it: whole vs part now exceeds 2 % wherever the part's fit
# is itself more than about 2 % off (seeds 0, 1, 3, 4, 5, 6: 4.5, 3.8, 3.3, 2.6, 3.3, 2.9 %).
_PART_OFF = pytest.mark.xfail(strict=True, reason="the undisturbed part's own fit (a cap plus "
                              "rests) is 2.4–4.4 % from the truth; the whole fit, which shares "
                              "the shape with the disturbed span, is within 0.35 % of it "
                              "(test_coherent_disturbance_whole_fit_recovers_the_truth)")


@pytest.mark.parametrize("seed", [2, 7] + [pytest.param(s, marks=_PART_OFF)
                                          for s in (0, 1, 3, 4, 5, 6)])
def test_coherent_disturbance_whole_fit_matches_its_undisturbed_part(seed):
    m, disturbed = coherent_track(seed)
    whole = fit(m, check_coverage=False)
    part = fit(m[~disturbed], check_coverage=False)
    # the criterion for BROAD 32: within 2 % (eq. 40) of the undisturbed part's fit
    assert model_error(whole.K, whole.b, part.K, part.b) < 0.02
    assert (~whole.inliers[disturbed]).mean() > 0.5


@pytest.mark.parametrize("seed", range(8))
def test_coherent_disturbance_whole_fit_recovers_the_truth(seed):
    m, disturbed = coherent_track(seed)
    whole = fit(m, check_coverage=False)
    part = fit(m[~disturbed], check_coverage=False)
    err, part_err = (model_error(c.K, c.b, K_TRUE, B_TRUE) for c in (whole, part))
    # the disturbed span (three quarters of the sphere) pins the shared shape: the support-only
    # fit was 1.3–5.1 % from the truth, the shared shape is within 0.35 %
    assert err < 0.01, (err, part_err)
    assert err <= part_err
    # the calibration is the undisturbed environment's: the disturbed samples stay outliers
    assert (~whole.inliers[disturbed]).mean() > 0.5
    assert whole.inliers[~disturbed].mean() > 0.95


def test_shift_start_recovers_the_offset_of_a_contaminated_shell():
    rng = np.random.default_rng(5)
    n = 2000
    x = cap(rng, n, 120, [0, 0, 1])
    m = x @ K_TRUE.T + B_TRUE + SHIFT + NOISE * rng.standard_normal((n, 3))
    m[:200] -= SHIFT                              # a tenth from the other shell (a mixed edge)
    delta = shift_start(K_TRUE, B_TRUE, m)
    assert np.linalg.norm(delta - SHIFT) < 0.5     # µT, against a 55 µT shift and 0.7 µT noise


def test_a_disturbance_that_is_not_a_shift_keeps_the_support_fit(monkeypatch):
    # soft iron in the disturbed span (its shape 15 % larger): one shape cannot fit both shells,
    # the check rejects the shared shape and the support-only fit is returned unchanged
    m, disturbed = coherent_track(1)
    x = np.linalg.solve(K_TRUE, (m[disturbed] - B_TRUE - SHIFT).T).T
    m[disturbed] = x @ (1.15 * K_TRUE).T + B_TRUE + SHIFT
    whole = fit(m, check_coverage=False)
    autocal_module = importlib.import_module("streamcal.fitting.autocal")
    monkeypatch.setattr(autocal_module, "consistent", lambda *a, **k: False)
    support_only = fit(m, check_coverage=False)
    assert np.array_equal(whole.K, support_only.K) and np.array_equal(whole.b, support_only.b)
    assert (~whole.inliers[disturbed]).mean() > 0.5


# --- BROAD trial 32: a magnet riding on the board for t in [38, 95] s --------------------------

def _broad32(real_tracks_dir):
    from streamcal.inputs.track import Track

    track = Track.read(real_tracks_dir / "broad_32_attached_magnet_1cm.csv.gz")
    t = track.t_mag
    return np.asarray(track.mag, float), t, (t < 34.0) | (t > 100.0), (t >= 38.0) & (t <= 95.0)


def test_broad32_start_lands_on_the_undisturbed_shell(real_tracks_dir):
    m, t, calm, magnet = _broad32(real_tracks_dir)
    part = fit(m[calm], check_coverage=False)
    m_n, center, scale = normalize(m)
    K0, b0, contaminated = plain_start(m_n)
    assert contaminated
    before = model_error(scale * K0, scale * b0 + center, part.K, part.b)
    choice = coherent_start(K0, b0, m_n)
    assert choice is not None
    K = scale * choice.K * np.sign(np.diag(choice.K))[None, :]
    after = model_error(K, scale * choice.b + center, part.K, part.b)
    # the magnet shell is ≈ 90 % away (eq. 40); within 10 % the LM on the support converges to
    # the undisturbed fit (measured: start 6.7 %, refined 1.6 %)
    assert after < 0.10 < before
    assert choice.support[magnet].mean() < 0.05      # one mixed chunk at most
    assert choice.support[calm].mean() > 0.90


def test_broad32_whole_fit_matches_its_undisturbed_part(real_tracks_dir):
    m, t, calm, magnet = _broad32(real_tracks_dir)
    whole, part = fit(m, check_coverage=False), fit(m[calm], check_coverage=False)
    assert model_error(whole.K, whole.b, part.K, part.b) < 0.02     # the target


# --- uniform outliers and clean data: the coherent search stays out of the way ----------------

@pytest.mark.parametrize("sigma,eta", [(1.0, 0.0), (0.5, 0.0)])
def test_clean_data_do_not_trigger_the_extra_path(sigma, eta):
    for seed in range(3):
        m, K, b, _ = paper_protocol(1000, sigma, eta, seed)
        _, _, contaminated = plain_start(normalize(m)[0])
        assert not contaminated


def test_clean_track_with_rest_periods_does_not_trigger_the_extra_path():
    rng = np.random.default_rng(3)
    n = 3000
    rest = np.tile(np.array([[0.2, -0.1, 0.97]]) / np.linalg.norm([0.2, -0.1, 0.97]), (n // 3, 1))
    x = rng.standard_normal((n - 2 * len(rest), 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = np.vstack([rest, x, rest]) @ K_TRUE.T + B_TRUE + NOISE * rng.standard_normal((n, 3))
    m_n = normalize(m)[0]
    K0, b0, contaminated = plain_start(m_n)
    assert not contaminated
    assert coherent_start(K0, b0, m_n) is None   # even if asked, the chunks all agree


@pytest.mark.parametrize("sigma,eta", [(2.0, 0.30), (1.0, 0.70)])
def test_uniform_outliers_do_not_look_coherent(sigma, eta):
    for seed in range(3):
        m, K, b, _ = paper_protocol(1000, sigma, eta, seed)
        m_n = normalize(m)[0]
        K0, b0, _ = plain_start(m_n)
        assert coherent_start(K0, b0, m_n) is None


def test_paper_protocol_at_70_percent_outliers_still_recovers_the_model():
    ours, oracle = [], []
    for seed in range(5):
        m, K, b, inliers = paper_protocol(1000, 1.0, 0.70, seed)
        cal = fit(m, check_coverage=False)
        ours.append(model_error(cal.K, cal.b, K, b))
        ref = fit(m[inliers], kernel="l2", check_coverage=False)
        oracle.append(model_error(ref.K, ref.b, K, b))
    # the paper-protocol target at η = 70 % (tools/bench_paper_protocol.py)
    assert np.mean(ours) <= 1.5 * np.mean(oracle), (ours, oracle)


@pytest.mark.xfail(strict=True, reason="known limit: a cap plus rests hardly constrains the "
                   "shape, so a disturbance with a few % of soft iron (here the span's shape 5 % "
                   "larger) passes every consistency check and the shared shape adopts the "
                   "span's shape: 7.4 % from the truth against 3.6 % for the support-only fit")
def test_a_disturbance_with_slight_soft_iron_does_not_worsen_the_fit(monkeypatch):
    m, disturbed = coherent_track(0)
    x = np.linalg.solve(K_TRUE, (m[disturbed] - B_TRUE - SHIFT).T).T
    m[disturbed] = x @ (1.05 * K_TRUE).T + B_TRUE + SHIFT
    whole = fit(m, check_coverage=False)
    monkeypatch.setattr(importlib.import_module("streamcal.fitting.autocal"), "consistent",
                        lambda *a, **k: False)
    support_only = fit(m, check_coverage=False)
    assert (model_error(whole.K, whole.b, K_TRUE, B_TRUE)
            <= model_error(support_only.K, support_only.b, K_TRUE, B_TRUE) + 0.002)


# --- the robust start never picks a shell no magnetometer has -------------------------------

def test_a_thin_shell_through_the_outliers_is_not_a_start():
    # σ = 2, 30 % outliers, seed 70: a concentration run threaded a long thin ellipsoid
    # (cond(K) ≫ 3) through the outlier cloud with a lower 20 % radial quantile than the true
    # shell's, and the default fit ended 1 046 % off (every kernel did)
    m, K, b, inliers = paper_protocol(1000, 2.0, 0.30, 70)
    m_n, center, scale = normalize(m)
    K0, b0 = stage1(m_n, clean_start=True)
    K1, b1 = robust_start(K0, b0, m_n)
    assert anisotropy(K1) <= MAX_ANISOTROPY
    assert model_error(K1, b1, K / scale, (b - center) / scale) < 0.1
    cal = fit(m, check_coverage=False)
    oracle = fit(m[inliers], kernel="l2", check_coverage=False)
    assert model_error(cal.K, cal.b, K, b) < 1.5 * model_error(oracle.K, oracle.b, K, b)


def test_without_a_plausible_concentration_the_start_stands(monkeypatch):
    # every concentration run ends on a shell no magnetometer has: the start is returned
    import streamcal.fitting.robust_start as rs

    thin = np.diag([5.0, 1.0, 0.5])
    monkeypatch.setattr(rs, "concentrate", lambda K, b, m, steps=20: (thin, b + 1.0))
    m, _, _, _ = paper_protocol(600, 1.0, 0.0, 2)
    m_n = normalize(m)[0]
    K0, b0 = np.eye(3), np.zeros(3)
    K1, b1 = robust_start(K0, b0, m_n)
    assert K1 is K0 and b1 is b0
    assert anisotropy(thin) > MAX_ANISOTROPY
