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

from ..constants import HALF_NORMAL_MEDIAN
from ..errors import InsufficientDataError
from .ellipsoid import ellipsoid_to_model, fit_l2_ellipsoid, spread_subset

#: Radial scalings of the starting ellipsoid tried.
SCALES = (0.6, 0.8, 1.0, 1.25, 1.5)
#: Fraction of samples kept by each concentration step, and the quantile scored.
KEEP, SCORE_QUANTILE = 0.25, 0.2


def radial_error(K: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """| ‖K⁻¹(m_j − b)‖ − 1 | per sample (N,): the relative distance from the ellipsoid."""
    return np.abs(np.linalg.norm(np.linalg.solve(K, (m - b).T), axis=0) - 1.0)


#: cond(K) above which a start is implausible for a magnetometer.
MAX_ANISOTROPY = 3.0


def anisotropy(K: np.ndarray) -> float:
    """cond(K): the ratio of the sensor matrix's largest to smallest singular value."""
    s = np.linalg.svd(K, compute_uv=False)
    return float(s[0] / max(s[-1], 1e-300))


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
    """Best (K, b) by :func:`lqs_score` over concentration runs from scaled copies of (K0, b0),
    among those a magnetometer could have (cond(K) ≤ MAX_ANISOTROPY); (K0, b0) when none is.

    Works on at most ``n_max`` samples spread over directions: a board resting in one pose
    gives a dense cluster that any thin shell through it would "fit" with a tiny score."""
    m = m[spread_subset(m, n_max)]
    best = None
    for scale in SCALES:
        K, b = concentrate(K0 * scale, b0, m)
        if anisotropy(K) > MAX_ANISOTROPY:
            # the scale-free score favours a long thin shell threaded through the outliers
            continue
        score = lqs_score(K, b, m)
        if best is None or score < best[0]:
            best = (score, K, b)
    if best is None:
        return K0, b0
    return best[1], best[2]


# ---------------------------------------------------------------------------------------------
# Coherent disturbances (a magnet riding on the board for a while).
#
# While the disturbance lasts the hard iron is shifted, so those samples lie on a second,
# coherent shell. When it is seen from more directions than the undisturbed part (a cap), every
# global start lands between the two shells and the robust LM threads a long, thin ellipsoid
# through both. What tells the two apart is time: a disturbance occupies a contiguous stretch.
# So the track (in sample order) is cut into contiguous chunks; each chunk that spreads over
# directions gives a sphere candidate (4 parameters: far better conditioned on a cap than 9),
# every candidate is grown over the chunks that agree with it (≥ AGREE of their samples within
# 3σ̂ of its surface) and refined by a short Geman–McClure LM on those chunks only, and the
# candidate whose agreeing chunks hold the most samples wins. Rest periods cannot make a
# candidate (their chunks do not spread) but they do vote: a board resting undisturbed lies on
# the undisturbed shell. On a cap, the full ellipsoid grown from the global start can agree with
# the same chunks as a cap sphere while bridging towards the disturbed shell (its 9 parameters
# are poorly fixed by a cap), so a tie on time goes to a sphere.
# ---------------------------------------------------------------------------------------------

from dataclasses import dataclass  # noqa: E402
from math import comb  # noqa: E402

from .kernels import make_kernel  # noqa: E402
from .lm import refine  # noqa: E402

#: Contiguous chunks the (subsampled) track is cut into, and the fewest samples per chunk.
MAX_CHUNKS, MIN_CHUNK = 24, 50
#: Samples (every k-th, in order) the chunk analysis works on.
N_EVAL = 6000
#: A chunk agrees with a model when at least this fraction of its samples lies within the band.
AGREE = 0.5
#: Coherent search when the chunks' inlier fractions under the plain start differ by more than
#: this (uniform outliers give every chunk about the same fraction: binomial spread, ~0.3 at 50
#: samples per chunk and 24 chunks) ...
HETEROGENEITY = 0.5
#: ... or by more than CONTIGUOUS_SPREAD (the binomial spread) with the bad chunks (below the
#: midpoint of the fractions) contiguous in time: one run of them at least RUN_SHARE of the
#: chunks long, a run that a random order of the same chunks (exchangeable, as uniform outliers
#: are) would give with probability below RUN_P. A start lying between two shells sees the
#: disturbed chunks only part-inside, so their fractions can differ from the rest's by little
#: more than the binomial spread; their contiguity is what gives the disturbance away.
CONTIGUOUS_SPREAD, RUN_SHARE, RUN_P = 0.3, 0.25, 1e-3
#: A chunk yields a sphere when its points spread (std along the 2nd and 3rd principal axes)
#: over at least these fractions of the sphere's radius.
MIN_SPREAD, MIN_DEPTH = 0.15, 0.02
#: Band half-width in units of the noise σ̂, and the GM width (95 % efficiency) of the short LM.
BAND, GM_TAU = 3.0, 3.787


@dataclass(frozen=True)
class StartChoice:
    """A start (normalized units) chosen by :func:`coherent_start`.

    ``support`` (N,) bool: the samples of the time chunks that agree with it (the undisturbed
    part as far as the start can tell); ``score`` the fraction of samples in those chunks;
    ``band`` the half-width of the band (relative radial error, see :func:`radial_error`) the
    chunks were judged with."""

    K: np.ndarray
    b: np.ndarray
    support: np.ndarray
    score: float
    band: float


def fit_sphere(m: np.ndarray):
    """Algebraic sphere ‖m‖² = 2c·m + k (linear in c, k; r² = k + ‖c‖²) → (r·I, c) or None."""
    A = np.column_stack([2.0 * m, np.ones(len(m))])
    sol = np.linalg.lstsq(A, np.einsum("ij,ij->i", m, m), rcond=None)[0]
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return np.sqrt(r2) * np.eye(3), c


def trimmed_sphere(m: np.ndarray, steps: int = 4):
    """Sphere refitted to the nearer half of the samples ``steps`` times (a chunk may hold the
    start or end of a disturbance)."""
    model = fit_sphere(m)
    for _ in range(steps):
        if model is None:
            return None
        e = radial_error(*model, m)
        near = m[e <= np.median(e)]
        if len(near) < 8:
            return None
        model = fit_sphere(near)
    return model


def _chunk_fractions(e: np.ndarray, chunk: np.ndarray, n_chunks: int, delta: float):
    inside = e < delta
    count = np.bincount(chunk, minlength=n_chunks)
    frac = np.bincount(chunk, weights=inside, minlength=n_chunks) / np.maximum(count, 1)
    return frac, count


def longest_run_probability(n: int, k: int, run: int) -> float:
    """P(the longest run of ones ≥ ``run``) for k ones placed in random order among n slots.

    Counts the arrangements whose n − k + 1 gaps between zeros each hold fewer than ``run``
    ones (inclusion–exclusion over the gaps that overflow)."""
    if run <= 0:
        return 1.0
    if run > k:
        return 0.0
    gaps = n - k + 1
    short = sum((-1) ** j * comb(gaps, j) * comb(k - j * run + gaps - 1, gaps - 1)
                for j in range(k // run + 1))
    return 1.0 - short / comb(n, k)


def contiguous_bad_chunks(frac: np.ndarray) -> bool:
    """Do the chunks that fit worst (fractions ``frac`` (n_chunks,) below the midpoint of their
    range) form one long run in time that a random order would hardly give (see RUN_P)?"""
    if frac.max() - frac.min() <= CONTIGUOUS_SPREAD:
        return False
    bad = frac < 0.5 * (frac.max() + frac.min())
    # longest run of True: distances between the False positions (padded at both ends)
    edges = np.flatnonzero(np.concatenate([[True], ~bad, [True]]))
    run = int(np.diff(edges).max()) - 1
    n = len(frac)
    return run >= RUN_SHARE * n and longest_run_probability(n, int(bad.sum()), run) < RUN_P


def _sigma(e: np.ndarray) -> float:
    return max(float(np.median(e)) / HALF_NORMAL_MEDIAN, 1e-9) if len(e) else np.inf


def _sphere_candidates(ev: np.ndarray, chunk: np.ndarray, n_chunks: int) -> list:
    """One trimmed sphere per chunk that spreads over directions; near-duplicates dropped."""
    ref = float(np.median(np.linalg.norm(ev - np.median(ev, axis=0), axis=1)))
    out: list = []
    for c in range(n_chunks):
        p = ev[chunk == c]
        if len(p) < 12:
            continue
        model = trimmed_sphere(p)
        if model is None:
            continue
        r = model[0][0, 0]
        w = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(p.T)), 0.0))
        if not 0.25 * ref < r < 4.0 * ref or w[1] < MIN_SPREAD * r or w[0] < MIN_DEPTH * r:
            continue
        if any(abs(K[0, 0] - r) < 0.05 * r and np.linalg.norm(b - model[1]) < 0.05 * r
               for K, b in out):
            continue
        out.append(model)
    return out


def _grow(K, b, ev, chunk, n_chunks, structure: str = "full", rounds: int = 3, n_fit: int = 600):
    """Refine (K, b) on the chunks that agree with it: (agreeing chunks → short GM LM on a
    direction-spread subset of their samples) × ``rounds``. Returns (K, b, σ̂) or None."""
    e = radial_error(K, b, ev)
    sigma = _sigma(np.sort(e)[: max(len(e) // 4, 12)]) * HALF_NORMAL_MEDIAN / 0.3186
    for _ in range(rounds):
        frac, _ = _chunk_fractions(e, chunk, n_chunks, BAND * sigma)
        keep = (frac >= AGREE)[chunk] & (e < BAND * sigma)
        if keep.sum() < 12:
            return None
        sub = ev[keep][spread_subset(ev[keep], n_fit)]
        r = float(np.cbrt(abs(np.linalg.det(K))))
        x = np.linalg.solve(K, (sub - b).T).T
        x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
        res = refine(sub, K, b, x, kernel=make_kernel("gm", GM_TAU * sigma * r),
                     structure=structure, max_iter=30, rtol=1e-4)
        if not np.all(np.isfinite(res.K)) or np.any(np.abs(np.diag(res.K)) < 1e-9):
            return None
        K, b = res.K * np.sign(np.diag(res.K))[None, :], res.b
        e = radial_error(K, b, ev)
        frac, _ = _chunk_fractions(e, chunk, n_chunks, BAND * sigma)
        sigma = _sigma(e[(frac >= AGREE)[chunk] & (e < BAND * sigma)])
    return K, b, sigma


def coherent_start(K0: np.ndarray, b0: np.ndarray, m: np.ndarray) -> StartChoice | None:
    """Look for a coherent disturbance; None when the data show none (the common case).

    ``m`` (N,3) normalized measurements in time order, (K0, b0) the start chosen so far. The
    search runs only when the chunks' inlier fractions under (K0, b0) are heterogeneous, or less
    so but with the worst-fitting chunks contiguous in time (see HETEROGENEITY and
    :func:`contiguous_bad_chunks`); candidates: (K0, b0) and the chunk spheres, each grown as
    in the section comment; those with cond(K) > MAX_ANISOTROPY are dropped; the winner has
    the most samples in chunks agreeing with it within a common band (BAND × the smallest σ̂ of
    the candidates), ties (the same chunks) going to a sphere, then to the most samples inside
    the band.
    """
    n = len(m)
    step = max(1, -(-n // N_EVAL))
    n_chunks = min(MAX_CHUNKS, (n // step) // MIN_CHUNK)
    if n_chunks < 6:
        return None
    full_chunk = (np.arange(n) * n_chunks) // n
    ev, chunk = m[::step], full_chunk[::step]
    e0 = radial_error(K0, b0, ev)
    sigma0 = float(np.quantile(e0, KEEP)) / 0.3186
    frac0, _ = _chunk_fractions(e0, chunk, n_chunks, BAND * sigma0)
    if frac0.max() - frac0.min() <= HETEROGENEITY and not contiguous_bad_chunks(frac0):
        return None
    grown = []
    starts = [(K0, b0, "full")] + [(K, b, "sphere") for K, b in _sphere_candidates(ev, chunk, n_chunks)]
    for K, b, structure in starts:
        g = _grow(K, b, ev, chunk, n_chunks, structure)
        if g is not None and anisotropy(g[0]) <= MAX_ANISOTROPY:
            grown.append((*g, structure))
    if not grown:
        return None
    delta = BAND * min(g[2] for g in grown)
    ranked = []
    for K, b, _, structure in grown:
        e = radial_error(K, b, ev)
        frac, count = _chunk_fractions(e, chunk, n_chunks, delta)
        agree = frac >= AGREE
        score = float(count[agree].sum() / count.sum())
        inside = float(np.mean(agree[chunk] & (e < delta)))
        choice = StartChoice(K, b, agree[full_chunk], score, delta)
        ranked.append((score, structure == "sphere", inside, choice))
    # Candidates agreeing with the same chunks (within half a chunk of the best) are tied on
    # time; a sphere wins such a tie (on a cap, a full ellipsoid grown from the global start can
    # explain the same chunks while bridging towards the disturbed shell), then the most samples
    # inside the band.
    top = max(r[0] for r in ranked)
    tied = [r for r in ranked if r[0] >= top - 0.5 / n_chunks]
    return max(tied, key=lambda r: (r[1], r[2]))[3]
