"""The gyro link: K and b parameters from the rotation rate between readings (issue #10).

The physics
-----------
With h = K⁻¹(m − b) the field in the body (magnetometer) frame, a constant Earth field seen from
a board turning at the body rate ω (rad/s) moves as ḣ = −ω × h. Written on the readings,
K⁻¹ṁ + ω × K⁻¹(m − b) = 0: with A = K⁻¹ and c = A b it is linear and homogeneous in (A, c) —
the relation behind the MAGYC methods (Rodríguez et al., "MAGYC: magnetometer and gyroscope
calibration", the ``magyc`` package). Rotation keeps ‖h‖, so it fixes the *shape* of K and the
offset b but not the overall scale of K (K → sK leaves it unchanged): the scale must come from
the sphere fit or a held value. b is seen only across the rotation axes present: a term
ω × Δh is blind to Δh along ω, so a yaw-only slice cannot see b_z this way (only through
the off-diagonal K, weakly).

The scheme (integrated, over a horizon)
---------------------------------------
The derivative form over consecutive samples (ṁ ≈ (m_{j+1} − m_j)/Δt, ω averaged over the pair)
divides the reading noise by Δt: at 100 Hz and σ = 0.4 µT, ṁ has 57 µT/s of noise per axis
while a 1 µT offset error at 0.5 rad/s moves it by 0.5 µT/s. Integrating ḣ = −ω × h between
two samples a and b (b the first sample at least ``horizon`` after a) gives the exact
h_b = Q_bᵀ Q_a h_a, Q the orientation integrated from the gyro (midpoint rule on the gyro rows,
Q_{i+1} = Q_i exp(ω̄_i Δt_i), ω̄_i the average of rows i and i+1; slerp to the magnetometer
instants), so the pair residual, in the sensor unit, is

    r_ab = (m_b − b) − K R_ab K⁻¹ (m_a − b),      R_ab = Q_bᵀ Q_a                  (1)

with noise ≈ σ√2 per axis whatever the horizon, and sensitivity to an offset error
(I − K R_ab K⁻¹) Δb, about the angle turned over the pair. ``horizon`` = 0 is the consecutive
(derivative) scheme. The gyro's own bias c and per-axis gain error g are nuisance parameters
(ω_true = (1 + g) ⊙ ω − c), fitted with the chosen K/b entries. No lag between gyro and
magnetometer is modelled (see :mod:`streamcal.fitting.gyro_lag`).

The fit and its uncertainty
---------------------------
Gauss–Newton on (1) over the chosen entries (named as in
:mod:`streamcal.fitting.entries`: ``K_xx … K_zz`` upper-triangular, ``b_x b_y b_z``) and the six
gyro nuisances, every other entry fixed at its given value; central-difference Jacobian (for
the nuisances, ∂R/∂(c, g) once per pair set at c = g = 0, :meth:`LinkPairs.rotation_steps`);
at most :data:`MAX_PAIRS` pairs, evenly spaced. With a :class:`SpherePrior` the sphere
(normal) residual, linearised, is added in χ² units (joint fit: the link alone cannot fix the
scale);
Cauchy weights on ‖r_ab‖ of width :data:`~streamcal.constants.CAUCHY_C` σ̂ (σ̂ per axis from the
median ‖r_ab‖).
Consecutive pairs share samples, so the residuals are correlated over a horizon: the
covariance is the sandwich H⁻¹ (Σ_B s_B s_Bᵀ) H⁻¹ with the weighted scores s summed over time
blocks of :data:`BLOCK_HORIZONS` horizons (at least 1 s; pairs more than a horizon
apart share no reading), and each standard error is the larger
of that and the independent-pairs σ̂²H⁻¹. A direction of H with eigenvalue below
:data:`NULL_RATIO` of the largest is unobservable: the entries on it get σ = inf.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..constants import CAUCHY_C, OUTLIER_WIDTHS
from ..errors import InsufficientDataError
from .entries import B_INDEX, K_INDEX, entry, with_entries
from .gyro_rates import clear_of_saturation, fresh, horizon_pairs, integrate_rates

#: Seconds between the two readings of a pair (0: consecutive readings).
HORIZON_S = 1.0
#: Sandwich blocks: this many horizons long, at least 1 s.
BLOCK_HORIZONS = 2
GN_ROUNDS, RTOL = 12, 1e-8
#: Gauss–Newton also stops after a step below this fraction of every (independent-pairs) σ.
STEP_STOP = 0.01
NULL_RATIO = 1e-9
#: Gaps longer than this many typical magnetometer periods break a pair.
GAP_FACTOR = 3.0
N_GYRO = 6
MIN_PAIRS = 30
#: Most pairs used (evenly spaced in time).
MAX_PAIRS = 3000


@dataclass
class LinkFit:
    """Outcome of :func:`link_fit` (sensor unit). ``estimated``: {name: (value, σ)};
    ``gyro_bias`` (3,) rad/s and ``gyro_gain`` (3,) the fitted nuisances; ``rms`` the residual
    (1) over inlier pairs (‖r‖ ≤ 2 widths), ``rms_still`` the same pairs predicted with no
    rotation (R = I) — a gyro that explains the motion has ``rms`` well below it;
    ``pair_t`` (P,) the instant of each pair's first reading, ``r`` (P,3) its residual."""

    K: np.ndarray
    b: np.ndarray
    estimated: dict
    gyro_bias: np.ndarray
    gyro_gain: np.ndarray
    rms: float
    rms_still: float
    sigma: float
    tau: float
    n_pairs: int
    horizon_s: float
    pair_t: np.ndarray = field(repr=False, default=None)
    r: np.ndarray = field(repr=False, default=None)
    iterations: int = 0
    #: (n,n) H and the block meat over (entries, gyro bias, gyro gain), χ² units.
    bread: np.ndarray = field(repr=False, default=None)
    meat: np.ndarray = field(repr=False, default=None)


class LinkPairs:
    """Pairs (a, b) of magnetometer readings ``m`` (N,3) at ``t`` (N,) s about ``horizon`` apart
    and the gyro rows ``t_g`` (G,) s, ``w_g`` (G,3) rad/s (magnetometer frame) that link them.
    A pair is dropped when it spans a gap, leaves the gyro's span, crosses a saturated gyro
    row, or either reading is a sample-and-hold repeat (the pairing, saturation test and
    integration are :mod:`.gyro_rates`'s, shared with :class:`~.gyro_lag.GyroPairs`)."""

    def __init__(self, m, t, t_g, w_g, horizon: float = HORIZON_S):
        self.m, self.t = np.asarray(m, float), np.asarray(t, float)
        self.t_g, self.w_g = np.asarray(t_g, float), np.asarray(w_g, float)
        n = len(self.t)
        if n < 3 or len(self.t_g) < 3:
            raise InsufficientDataError("the gyro link needs at least 3 magnetometer readings "
                                        "and 3 gyro rows")
        period = float(np.median(np.diff(self.t)))
        a, b = horizon_pairs(self.t, horizon)
        gaps = np.concatenate([[0], np.cumsum(np.diff(self.t) > GAP_FACTOR * period)])
        ok = gaps[b] == gaps[a]
        ok &= (self.t[a] >= self.t_g[0]) & (self.t[b] <= self.t_g[-1])
        ok &= clear_of_saturation(self.t_g, self.w_g, self.t[a], self.t[b])
        fr = fresh(self.m)
        ok &= fr[a] & fr[b]
        a, b = a[ok], b[ok]
        # overlapping pairs a sample apart add little over a few per horizon: keep at most
        # MAX_PAIRS, evenly spaced
        stride = max(1, int(np.ceil(len(a) / MAX_PAIRS)))
        self.a, self.b = a[::stride], b[::stride]
        if len(self.a) < MIN_PAIRS:
            raise InsufficientDataError(f"{len(self.a)} usable reading pairs are too few for "
                                        f"the gyro link (at least {MIN_PAIRS})")
        self.horizon = float(np.median(self.t[self.b] - self.t[self.a]))

    def __len__(self) -> int:
        return len(self.a)

    def rotations(self, bias, gain) -> np.ndarray:
        """(P,3,3) R_ab = Q_bᵀ Q_a from the corrected rates (1 + gain) ⊙ ω − bias (every fit
        starts at zero bias and gain error: that one is kept)."""
        zero = not (np.any(bias) or np.any(gain))
        if zero and getattr(self, "_R0", None) is not None:
            return self._R0
        orient = integrate_rates(self.t_g, self.w_g * (1.0 + np.asarray(gain)) - np.asarray(bias))
        Qa = orient.at(self.t[self.a]).as_matrix()
        Qb = orient.at(self.t[self.b]).as_matrix()
        R = np.einsum("pji,pjk->pik", Qb, Qa)
        if zero:
            R.flags.writeable = False
            self._R0 = R
        return R

    def rotation_steps(self) -> np.ndarray:
        """(N_GYRO,P,3,3) ∂R_ab/∂(bias, gain) at zero bias and gain error, central differences
        (re-integrated), computed once: the nuisances are small and barely move it."""
        if getattr(self, "_dR", None) is None:
            out, step = [], 1e-5
            for k in range(N_GYRO):
                e = np.zeros(N_GYRO)
                e[k] = step
                out.append((self.rotations(e[:3], e[3:]) - self.rotations(-e[:3], -e[3:]))
                           / (2 * step))
            self._dR = np.stack(out)
        return self._dR

    def residual(self, K, b, R, sel=None) -> np.ndarray:
        """(P,3) residual (1), sensor unit, of the pairs ``sel`` (default all); ``R`` the
        rotations of those pairs."""
        a, bb = (self.a, self.b) if sel is None else (self.a[sel], self.b[sel])
        h_a = np.linalg.solve(K, (self.m[a] - b).T).T
        return (self.m[bb] - b) - np.einsum("ij,pjk,pk->pi", K, R, h_a)


def _width(rn):
    """Per-axis σ̂ from the median pair-residual norm (χ₃ median 1.538 σ)."""
    return max(float(np.median(rn)) / 1.538, 1e-12)


@dataclass
class SpherePrior:
    """The sphere (normal) residual linearised at K0, b0 for the entries ``names``: cost
    δᵀ F δ − 2 cᵀ δ (+ const) in χ² units, δ the change of those entries (sensor unit);
    F = AᵀWA/σ², c = AᵀWs/σ² (A the rows ∂(−s)/∂p, s the signed normal residual, W its robust
    weights, σ its noise)."""

    names: list
    F: np.ndarray
    c: np.ndarray


def link_fit(pairs: LinkPairs, K0, b0, names: Sequence[str], sel=None,
             scale: float | None = None, sphere: SpherePrior | None = None,
             rounds: int = GN_ROUNDS) -> LinkFit:
    """Fit the entries ``names`` of (K, b) (every other entry at ``K0``/``b0``) and the gyro's
    bias and gain error on the residual (1) of the pairs ``sel`` (default all); see the module
    doc. ``scale``: the field radius (sets the difference steps; default from diag K0).
    ``sphere``: fit jointly with the linearised sphere residual (entries of ``sphere.names``
    missing from ``names`` stay at K0, b0): the link in χ² units (Cauchy cost × C², per-axis
    σ̂ fixed at the start's) plus the sphere's quadratic; the covariance adds F to both the
    bread and the meat of the sandwich. ``rounds`` = 0 evaluates the start (its ``bread`` and
    ``meat`` give the errors of any subset, :func:`subset_errors`)."""
    K0, b0 = np.asarray(K0, float), np.asarray(b0, float)
    names = list(names)
    for n in names:
        if n not in K_INDEX and n not in B_INDEX:
            raise ValueError(f"unknown parameter {n!r}")
    r_scale = scale or float(np.prod(np.abs(np.diag(K0))) ** (1 / 3))
    sel = np.arange(len(pairs)) if sel is None else np.asarray(sel)
    p = np.concatenate([[entry(K0, b0, n) for n in names], np.zeros(N_GYRO)])
    nk = len(names)
    steps = np.full(nk, 1e-4 * r_scale)   # central-difference steps of the K/b entries

    def rot(q):
        return pairs.rotations(q[nk:nk + 3], q[nk + 3:])

    def res(q, R):
        K, b = with_entries(K0, b0, names, q[:nk])
        return pairs.residual(K, b, R, sel)

    def evaluate(q):
        R = rot(q)[sel]
        return R, res(q, R)

    Fp, cp = _prior(sphere, names, len(p))
    p0 = p.copy()

    def quad(q):
        d = q - p0
        return float(d @ Fp @ d - 2 * cp @ d)

    R, r = evaluate(p)
    dR = pairs.rotation_steps()[:, sel]

    def jac(q):
        K, b = with_entries(K0, b0, names, q[:nk])
        h_a = np.linalg.solve(K, (pairs.m[pairs.a[sel]] - b).T).T
        return _jacobian(q, nk, steps, R, res, dR, h_a, K)

    sig0 = _width(np.linalg.norm(r, axis=1))
    tau = CAUCHY_C * sig0

    def total(r_, q):
        return CAUCHY_C ** 2 * np.sum(np.log1p(np.sum(r_ * r_, 1) / tau ** 2)) + quad(q)

    cost = total(r, p)
    it = 0
    # Not fitting.damped_lm: entries the rotation does not see leave H singular by design, and
    # their step must be zero (the pseudo-inverse step, halved until the cost falls), where
    # damped_lm's λ·diag H regularisation would move them freely.
    for it in range(1, rounds + 1):
        J = jac(p)
        w = 1.0 / (1.0 + np.sum(r * r, 1) / tau ** 2)
        H = np.einsum("p,pik,pil->kl", w, J, J) / sig0 ** 2 + Fp
        g = np.einsum("p,pik,pi->k", w, J, r) / sig0 ** 2 + Fp @ (p - p0) - cp
        Hi = pseudo_inverse(H)[0]
        dp = -Hi @ g
        small = bool(np.all(np.abs(dp) <= STEP_STOP * np.sqrt(np.maximum(np.diag(Hi), 0.0))))
        improved = False
        for _ in range(6):
            R_t, r_t = evaluate(p + dp)
            c_t = total(r_t, p + dp)
            if c_t < cost:
                rel = (cost - c_t) / max(cost, 1e-300)
                p, R, r, cost, improved = p + dp, R_t, r_t, c_t, True
                break
            dp = dp / 4
        if not improved or rel < RTOL or small:
            break
    rn = np.linalg.norm(r, axis=1)
    sigma = _width(rn)
    tau = CAUCHY_C * sigma
    J = jac(p)
    w = 1.0 / (1.0 + rn ** 2 / tau ** 2)
    sd, bread, meat = _errors(J, w, r, pairs.t[pairs.a[sel]], pairs.horizon, sigma, Fp)
    K, b = with_entries(K0, b0, names, p[:nk])
    inl = rn <= OUTLIER_WIDTHS * tau
    r_still = pairs.residual(K, b, np.broadcast_to(np.eye(3), (len(sel), 3, 3)), sel)
    return LinkFit(K=K, b=b, estimated={n: (float(v), float(e)) for n, v, e in
                                         zip(names, p[:nk], sd[:nk])},
                   gyro_bias=p[nk:nk + 3], gyro_gain=p[nk + 3:],
                   rms=float(np.sqrt(np.mean(rn[inl] ** 2))) if inl.any() else float("nan"),
                   rms_still=float(np.sqrt(np.mean(np.sum(r_still[inl] ** 2, 1))))
                   if inl.any() else float("nan"),
                   sigma=sigma, tau=tau, n_pairs=len(sel), horizon_s=pairs.horizon,
                   pair_t=pairs.t[pairs.a[sel]], r=r, iterations=it, bread=bread, meat=meat)


def _jacobian(p, nk, steps, R, res, dR, h_a, K):
    """(P,3,n): central differences in the K/b entries (the rotations ``R`` kept), and for the
    gyro nuisances −K (∂R/∂q) h_a with ``dR`` (N_GYRO,P,3,3) from
    :meth:`LinkPairs.rotation_steps`."""
    cols = []
    for k in range(nk):
        e = np.zeros(len(p))
        e[k] = steps[k]
        cols.append((res(p + e, R) - res(p - e, R)) / (2 * steps[k]))
    for d in dR:
        cols.append(-np.einsum("ij,pjk,pk->pi", K, d, h_a))
    return np.stack(cols, axis=2)


def pseudo_inverse(H: np.ndarray):
    """(H⁺ (P,P), on_null (P,) bool) of a symmetric H: the eigen pseudo-inverse without the
    eigenvalues ≤ NULL_RATIO × the largest, and the parameters with a share (component² >
    1e-6) in those dropped directions — the ones the data do not determine."""
    ev, V = np.linalg.eigh(H)
    null = ev <= max(ev[-1], 1e-300) * NULL_RATIO
    Hinv = (V * np.where(null, 0.0, 1.0 / np.where(null, 1.0, ev))) @ V.T
    on_null = (V[:, null] ** 2).sum(axis=1) > 1e-6 if null.any() else np.zeros(len(H), bool)
    return Hinv, on_null


def _prior(sphere, names, n):
    """(F, c) of ``sphere`` on the parameter vector (entries of ``names``, then the gyro's)."""
    F, c = np.zeros((n, n)), np.zeros(n)
    if sphere is None:
        return F, c
    idx = {nm: k for k, nm in enumerate(names)}
    src = [k for k, nm in enumerate(sphere.names) if nm in idx]
    dst = [idx[sphere.names[k]] for k in src]
    F[np.ix_(dst, dst)] = np.asarray(sphere.F)[np.ix_(src, src)]
    c[dst] = np.asarray(sphere.c)[src]
    return F, c


def _errors(J, w, r, t_pair, horizon, sigma, F) -> np.ndarray:
    """Standard errors (module doc): max(block sandwich, naive); inf on unobservable ones. The
    link in χ² units (÷ σ̂²) plus the sphere's information F."""
    H = np.einsum("p,pik,pil->kl", w, J, J) / sigma ** 2 + F
    Hinv, on_null = pseudo_inverse(H)
    scores = np.einsum("p,pik,pi->pk", w, J, r) / sigma ** 2
    block = max(BLOCK_HORIZONS * horizon, 1.0)
    ids = np.floor((t_pair - t_pair.min()) / block).astype(int)
    S = np.zeros((ids.max() + 1, J.shape[2]))
    np.add.at(S, ids, scores)
    nb = int(np.count_nonzero(np.any(S != 0, axis=1)))
    meat = S.T @ S * (nb / max(nb - J.shape[2], 1)) + F
    sandwich = np.diag(Hinv @ meat @ Hinv)
    naive = np.diag(Hinv)
    sd = np.sqrt(np.maximum(np.maximum(sandwich, naive), 0.0))
    if nb <= 2 * J.shape[2]:   # too few blocks to estimate the correlated spread
        sd = np.full(len(sd), np.inf)
    sd[on_null] = np.inf
    return sd, H, meat


def subset_errors(fit: LinkFit, keep: Sequence[int], sandwich: bool = False) -> np.ndarray:
    """Errors of the parameters ``keep`` (indices into the fit's vector) when the others are
    fixed, on the sub-blocks of ``fit.bread`` (and ``fit.meat`` with ``sandwich``: then
    max(sandwich, naive)); inf where unobservable; linearised at that fit. Without
    ``sandwich`` it is the information alone (Cramér–Rao, independent pairs): at a start point
    whose held values are wrong the residuals, hence the meat, carry that error."""
    keep = list(keep)
    H, M = fit.bread[np.ix_(keep, keep)], fit.meat[np.ix_(keep, keep)]
    Hinv, on_null = pseudo_inverse(H)
    var = np.diag(Hinv)
    if sandwich:
        var = np.maximum(np.diag(Hinv @ M @ Hinv), var)
    sd = np.sqrt(np.maximum(var, 0.0))
    sd[on_null] = np.inf
    return sd
