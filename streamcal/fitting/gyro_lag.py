"""``time_lag`` from the gyro alone: the gyro-tied residual and its fit (docs/effects.md
``time_lag``,
"needs gyro or accel"; DESIGN §3 "with the gyro, consecutive directions are linked by the
rotation rate").

The kinematics
--------------
A constant Earth field seen from a board turning at the body rate ω (rad/s, body frame) moves
as ẋ = −ω × x. Integrating the gyro gives the orientation Q(t) of the body relative to a frame
that follows the integrated gyro (Q(t) x(t) is constant there), so the direction at a later
instant is predicted from an earlier one:

    x̂_b = Q(t_b − τ)⁻¹ Q(t_a − τ) x_a                                            (1)

where x_j (unit, magnetometer frame) is the calibrated direction of magnetometer sample j
(``cal.apply``, renormalized) and τ (s) the lag: the sample stamped t_j was taken at t_j − τ, so
the gyro is read at t_j − τ (Q interpolated between the IMU rows by slerp).

The gyro-tied residual
----------------------
For every magnetometer sample a and the first sample b at least H = :data:`HORIZON_S` after it
(the next one when the rate is lower; 0.5 s, about the correlation time of a hand's rotation
rate; pairs spanning a gap are dropped),

    r_ab = K (x̂_b − x_b)                                            sensor unit, (3,)  (2)

the reading's error when sample b is predicted from sample a by the gyro, mapped to the sensor
by the fitted K (so it is in µT, or counts, like every other rms of the diagnosis). It is stored
at the earlier sample a (each a has one pair; jittered stamps can give two a's the same b), so
the last H seconds have none and count as outliers.

Why a horizon and not consecutive samples: a lag τ shifts the predicted rotation by about
τ·(ω(t_b) − ω(t_a)). Between consecutive samples (10 ms at 100 Hz) that is τ·α·Δt ≈ 1.5·10⁻³ rad
for τ = 30 ms and a hand's angular acceleration α ≈ 5 rad/s², beside a direction-noise
difference of ≈ 1.2·10⁻² rad: the rms would change by < 1 %, immaterial. Over H = 0.5 s it is
≈ τ·|ω(t_b) − ω(t_a)|, several times the noise for τ = 30 ms, while the gyro's own errors over H
(noise ≈ 10⁻⁴ rad; gains, frame and bias are fitted, below) stay small. Measured on the simulated
hand motion (40 s, σ = 0.4 µT, seed 53): base rms 0.81 µT at every horizon; with τ = 10 / 30 ms
it is 0.81 / 0.84, 0.83 / 1.03, 0.91 / 1.54, 1.03 / 2.12 µT for H = 0.05, 0.2, 0.5, 1 s.

The gyro's calibration
----------------------
The gyro reading is mapped to the magnetometer frame by a general 3×3 matrix and an offset,
ω' = M ω + c (frame rotation between the chips, gyro gains and non-orthogonality, bias: 12
nuisance parameters, the same in the fits with and without the lag). M, c start from the
orthogonal (frame) factor of a linear least-squares fit on consecutive pairs (Δx = [x̄]× θ with θ = M ∫ω + c Δt, the Cayley midpoint
form, unbiased to first order because the noise of x̄ and of Δx are uncorrelated), then
Gauss–Newton (Levenberg–Marquardt) on (2) over (M, c[, τ]): the Jacobian in (M, c) is
analytic — a perturbation δω of the rate turns the following frame by φ(t) = ∫ Q(s) δω(s) ds, so
∂x̂_b = Q_b⁻¹ ((φ_a − φ_b) × Q_a x_a), with ∫ Q(s) e_i ω_j(s) ds and ∫ Q(s) e_i ds cumulated once
per iteration on the IMU rows; the τ column is a central difference (:data:`LAG_STEP`).

τ is first located on the grid :data:`LAG_GRID` (±0.3 s; the cost is not convex in τ beyond a
fraction of the motion's correlation time) on at most :data:`GRID_PAIRS` pairs, then refined by
the Gauss–Newton steps. A minimum on the grid's edge means the data do not determine the lag
(InsufficientDataError).

Robust weights and the rms
--------------------------
Pairs are weighted by the fit's kernel (width from the median residual after the grid, as in
:mod:`streamcal.fitting.registration`, then held fixed so the robust cost stays one function);
pairs across a saturated gyro reading (:func:`.gyro_rates.saturated`) are dropped, and so are
sample-and-hold repeats of the magnetometer (:func:`fresh`); a pair is an inlier when both samples are inliers of the
free-direction fit and ‖r_ab‖ ≤ 2 kernel widths. ``rms`` is sqrt(mean ‖r_ab‖²) over inlier pairs,
in the sensor unit — computed the same way with and without the lag (same pairs, same 12
nuisance parameters), so the two are comparable; not with the free-direction rms (eq. 41),
which cannot see a lag at all. Without any effect (2) keeps the noise of two samples, ≈ 2σ.

K, b and the other effects come from the free-direction fit (``streamcal.fitting.fit``) of the rest
of the model: the lag leaves the ellipsoid residual unchanged, so it changes nothing there; it
matters where the direction is combined with the gyro, which is the residual (2).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import OUTLIER_WIDTHS
from ..errors import InsufficientDataError, MissingColumnsError
from ..model.build import check_known, terms_from_params
from .core import fit_core
from .damped_lm import damped_lm, lag_grid, search_lag, trimmed_cost
from .gyro_rates import (Orientation, clear_of_saturation, fresh, gyro_rates, horizon_pairs,
                         integrate_rates)
from .kernels import kernel_weights, width_from_residuals
from .registration_result import RegistrationFit

#: Time between the two samples of a pair (s).
HORIZON_S = 0.5
#: Grid of τ (s) searched before refining; its edge is the largest lag the fit accepts.
LAG_GRID = lag_grid(0.30)
MAX_LAG = 0.3
#: Most pairs used on the grid (the Gauss–Newton refinement uses them all).
GRID_PAIRS = 2000
LAG_STEP = 1e-3
GN_ROUNDS = 8
RTOL = 1e-6
#: Ridge pulling the gyro map towards (I, 0) when the motion leaves it undetermined, relative
#: to the mean diagonal of the normal matrix.
RIDGE = 1e-6
#: Gaps longer than this many typical periods break a pair.
GAP_FACTOR = 1.5
#: The gyro must predict the direction H later this much better (rms over the pairs) than
#: assuming no rotation, else it does not explain the direction changes (refused).
EXPLAINED = 0.5
#: Singular values of the fitted gyro map M outside this range mean the gyro does not explain
#: the direction changes (saturated, or not on the magnetometer's board): the fit is refused.
GAIN_RANGE = (0.7, 1.4)
N_GYRO_PARAMS = 12


def _interp_rows(t_query: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values`` (G, …) given at ``t`` (G,) to ``t_query`` (N,)."""
    i = np.clip(np.searchsorted(t, t_query) - 1, 0, len(t) - 2)
    f = np.clip((t_query - t[i]) / (t[i + 1] - t[i]), 0.0, 1.0)
    f = f.reshape((-1,) + (1,) * (values.ndim - 1))
    return values[i] * (1 - f) + values[i + 1] * f


def _cumtrapz(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of ``values`` (G, …) over ``t`` (G,), starting at 0."""
    dt = np.diff(t).reshape((-1,) + (1,) * (values.ndim - 1))
    steps = 0.5 * (values[1:] + values[:-1]) * dt
    return np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(steps, axis=0)])


class GyroPairs:
    """The pairs (a, b) of magnetometer samples ``HORIZON_S`` apart and the gyro that links them.

    ``x`` (N,3) unit directions (magnetometer frame), ``t`` (N,) stamps s, ``K`` (3,3) the
    sensor model, ``t_g`` (G,) / ``w`` (G,3) the gyro rows (rad/s). A pair is valid when no gap
    breaks it and both instants stay inside the gyro's span for every τ within ±MAX_LAG."""

    def __init__(self, x, t, K, t_g, w, horizon: float | None = None):
        horizon = HORIZON_S if horizon is None else horizon
        self.x, self.t, self.K = np.asarray(x, float), np.asarray(t, float), np.asarray(K, float)
        self.t_g, self.w = t_g, w
        n = len(self.t)
        period = float(np.median(np.diff(self.t))) if n > 1 else 1.0
        a, b = horizon_pairs(self.t, horizon)
        span = self.t[b] - self.t[a]
        inside = (self.t[a] - MAX_LAG - 2 * LAG_STEP >= t_g[0]) & \
                 (self.t[b] + MAX_LAG + 2 * LAG_STEP <= t_g[-1])
        ok = (span > 0) & (span <= GAP_FACTOR * max(horizon, period)) & inside
        ok &= clear_of_saturation(t_g, w, self.t[a] - MAX_LAG - 2 * LAG_STEP,
                                  self.t[b] + MAX_LAG + 2 * LAG_STEP)
        self.a, self.b = a[ok], b[ok]
        self.period = period
        #: median time between the samples of a pair (s)
        self.horizon = float(np.median(span[ok])) if ok.any() else float("nan")

    def __len__(self) -> int:
        return len(self.a)

    # -- the gyro map ------------------------------------------------------------------------
    def initial_map(self, lag_s: float) -> np.ndarray:
        """12 parameters (M row-major, c) from the linear Cayley fit on consecutive pairs."""
        j = np.arange(len(self.t) - 1)
        dt = np.diff(self.t)
        ok = (dt > 0) & (dt <= GAP_FACTOR * self.period) & \
             (self.t[j] - lag_s >= self.t_g[0]) & (self.t[j + 1] - lag_s <= self.t_g[-1])
        j, dt = j[ok], dt[ok]
        if len(j) < 12:
            raise InsufficientDataError("too few consecutive magnetometer samples within the "
                                        "gyro's span for the gyro-tied lag")
        phi = _cumtrapz(self.t_g, self.w)
        theta = _interp_rows(self.t[j + 1] - lag_s, self.t_g, phi) - \
            _interp_rows(self.t[j] - lag_s, self.t_g, phi)                      # (P,3) rad
        xm = self.x[j] + self.x[j + 1]
        xm /= np.linalg.norm(xm, axis=1, keepdims=True)
        dx = self.x[j + 1] - self.x[j]
        S = _skew(xm)                                                          # (P,3,3)
        design = np.concatenate([np.einsum("pik,pl->pikl", S, theta).reshape(len(j), 3, 9),
                                 S * dt[:, None, None]], axis=2)              # (P,3,12)
        p0 = _identity_map()
        w = np.ones(len(j))
        for _ in range(3):   # IRLS, Cauchy on the pair residual
            H = np.einsum("p,pik,pil->kl", w, design, design)
            g = np.einsum("p,pik,pi->k", w, design, dx)
            lam = RIDGE * np.trace(H) / 12
            p = np.linalg.solve(H + lam * np.eye(12), g + lam * p0)
            rn = np.linalg.norm(np.einsum("pik,k->pi", design, p) - dx, axis=1)
            s = width_from_residuals("cauchy", rn)
            w = 1.0 / (1.0 + (rn / s) ** 2)
        # Keep the frame, not the gains: readings held or bunched in time (irregular logging)
        # bias the gains of this short-step fit; the Gauss–Newton fit over H sets them.
        U, sv, Vt = np.linalg.svd(p[:9].reshape(3, 3))
        return np.concatenate([(U @ Vt).ravel(), p[9:] / max(float(np.mean(sv)), 1e-9)])

    def orientation(self, p: np.ndarray) -> "Orientation":
        """Q (body = magnetometer frame → gyro-following frame) from the mapped rates
        ω' = M ω + c, integrated on the gyro rows."""

        M, c = p[:9].reshape(3, 3), p[9:12]
        return integrate_rates(self.t_g, self.w @ M.T + c)

    # -- the residual (2) --------------------------------------------------------------------
    def residual(self, Q: "Orientation", lag_s: float, sel=None) -> np.ndarray:
        """(P,3) sensor-unit residual r_ab of the pairs ``sel`` (default all)."""
        a, b = (self.a, self.b) if sel is None else (self.a[sel], self.b[sel])
        Qa, Qb = Q.at(self.t[a] - lag_s), Q.at(self.t[b] - lag_s)
        xb_hat = Qb.apply(Qa.apply(self.x[a]), inverse=True)
        return (xb_hat - self.x[b]) @ self.K.T

    def map_jacobian(self, Q: "Orientation", lag_s: float, sel=None) -> np.ndarray:
        """(P,3,12) ∂r_ab/∂(M, c), analytic (module docstring)."""
        a, b = (self.a, self.b) if sel is None else (self.a[sel], self.b[sel])
        R = Rotation.from_quat(Q.quat).as_matrix()                              # (G,3,3)
        integrand = np.concatenate([np.einsum("gia,gb->giab", R, self.w).reshape(-1, 3, 9), R],
                                   axis=2)                                      # (G,3,12)
        F = _cumtrapz(self.t_g, integrand)
        ta, tb = self.t[a] - lag_s, self.t[b] - lag_s
        dphi = _interp_rows(ta, self.t_g, F) - _interp_rows(tb, self.t_g, F)   # φ_a − φ_b
        Qa, Qb = Q.at(ta), Q.at(tb)
        za = Qa.apply(self.x[a])
        turned = np.cross(dphi.transpose(0, 2, 1), za[:, None, :])             # (P,12,3)
        back = np.einsum("pji,pkj->pki", Qb.as_matrix(), turned)               # Q_b⁻¹ (…)
        return np.einsum("ij,pkj->pik", self.K, back)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3,3) cross-product matrices [v]×."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1),
                     np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def _identity_map() -> np.ndarray:
    return np.concatenate([np.eye(3).ravel(), np.zeros(3)])


def _n_base_params(cal) -> int:
    """Global parameters of a free-direction fit: K, b (at most 9) and the effect terms."""

    core = min(sum({"hard_iron": 3, "scale": 3, "soft_iron": 6}.get(n, 0) for n in cal.model), 9)
    return core + sum(t.n_params() for t, _ in terms_from_params(cal.effects))


def _grid(pairs: GyroPairs, Q: Orientation, sel: np.ndarray) -> tuple[float, np.ndarray]:
    """τ (s) minimizing the trimmed cost on :data:`LAG_GRID`, and the costs."""
    return search_lag(LAG_GRID, lambda lag_s: trimmed_cost(
        np.linalg.norm(pairs.residual(Q, lag_s, sel), axis=1)))


def fit_gyro_tied(pairs: GyroPairs, *, fit_lag: bool, kernel: str = "cauchy",
                  inlier_samples: np.ndarray | None = None, sel: np.ndarray | None = None,
                  lag0: float = 0.0) -> tuple[np.ndarray, float]:
    """Robust fit of the gyro map (12) and, if ``fit_lag``, τ (s) on the pairs ``sel`` whose
    samples are ``inlier_samples`` (N,) → (p (12,), τ, :class:`~.damped_lm.LMStatus`)."""
    use = np.arange(len(pairs)) if sel is None else np.asarray(sel)
    if inlier_samples is not None:
        use = use[inlier_samples[pairs.a[use]] & inlier_samples[pairs.b[use]]]
    if len(use) < 3 * (N_GYRO_PARAMS + 1):
        raise InsufficientDataError(f"{len(use)} sample pairs {HORIZON_S} s apart within the "
                                    "gyro's span are too few for the gyro-tied lag")
    lag_s = float(lag0)
    p = pairs.initial_map(lag_s)
    Q = pairs.orientation(p)
    if fit_lag:
        step = max(1, len(use) // GRID_PAIRS)
        lag_s, _ = _grid(pairs, Q, use[::step])
    r = pairs.residual(Q, lag_s, use)
    width = width_from_residuals(kernel, np.linalg.norm(r, axis=1))   # fixed: one robust cost

    def linearize(state, aux):   # IRLS: this round's weights define the merit
        (_, lag_s), (Q, r) = state, aux
        rn = np.linalg.norm(r, axis=1)
        w = kernel_weights(kernel, rn, width)
        J = pairs.map_jacobian(Q, lag_s, use)
        if fit_lag:
            jt = (pairs.residual(Q, lag_s + LAG_STEP, use) - pairs.residual(Q, lag_s - LAG_STEP, use)
                  ) / (2 * LAG_STEP)
            J = np.concatenate([J, jt[:, :, None]], axis=2)
        H = np.einsum("p,pik,pil->kl", w, J, J)
        g = np.einsum("p,pik,pi->k", w, J, r)
        return float(np.sum(w * rn ** 2)), H, g, w

    def propose(state, d):
        p, lag_s = state
        return p + d[:12], lag_s + (float(d[12]) if fit_lag else 0.0)

    def evaluate(state, w):
        p1, lag1 = state
        if abs(lag1) > MAX_LAG:
            return np.inf, None
        Q1 = pairs.orientation(p1)
        r1 = pairs.residual(Q1, lag1, use)
        return float(np.sum(w * np.sum(r1 * r1, axis=1))), (Q1, r1)

    lm = damped_lm((p, lag_s), (Q, r), np.inf, linearize=linearize, propose=propose,
                   evaluate=evaluate, max_iter=GN_ROUNDS, rtol=RTOL)
    (p, lag_s), (Q, r) = lm.x, lm.aux
    gains = np.linalg.svd(p[:9].reshape(3, 3), compute_uv=False)
    still = np.sqrt(np.mean(np.sum(((pairs.x[pairs.a[use]] - pairs.x[pairs.b[use]])
                                    @ pairs.K.T) ** 2, axis=1)))   # predicting "no rotation"
    if np.sqrt(np.mean(np.sum(r * r, axis=1))) > EXPLAINED * still or \
            gains.min() < GAIN_RANGE[0] or gains.max() > GAIN_RANGE[1]:
        raise InsufficientDataError(
            f"the gyro does not follow the magnetometer's direction changes: the fitted gyro "
            f"gains are {', '.join(f'{g:.2f}' for g in gains)} (expected ≈ 1; a saturated gyro "
            "or one that is not on the magnetometer's board)")
    if fit_lag and abs(lag_s) >= MAX_LAG - 0.5 * (LAG_GRID[1] - LAG_GRID[0]):
        raise InsufficientDataError(f"the time lag is not determined by the gyro: the fit went "
                                    f"to {lag_s:.3f} s, the edge of ±{MAX_LAG} s")
    return p, lag_s, lm


def gyro_lag_fit(track, model: Sequence[str], *, kernel: str = "cauchy", tau: float | None = None,
                 initial=None, rows: np.ndarray | None = None, lag: float = 0.0):
    """Gyro-tied fit of ``model`` on ``track`` (module docstring) →
    :class:`streamcal.fitting.registration.RegistrationFit` with the residual (2) per sample
    (stored at the earlier sample of each pair; none, and not inliers, in the last H seconds and
    at repeated readings), its inliers and rms; ``rotation`` is the polar
    factor of the fitted gyro map M, ``dip`` is NaN (not used), ``lag`` τ (0 without
    ``time_lag`` in ``model``).

    ``model`` may hold ``time_lag`` but not ``mag_accel_misalignment`` (that one needs the
    accelerometer). ``tau``: kernel width (sensor unit) for the free-direction fit. ``initial``:
    a Calibration of the non-registration part of the model to start from (or reuse when its
    model matches). ``rows``: magnetometer sample indices; only pairs starting there are fitted
    (the residuals, inliers and rms returned still cover every pair). ``lag``: the τ (s) used
    when ``time_lag`` is not in ``model`` (e.g. a lag known from another fit)."""

    names = check_known(model)
    if "mag_accel_misalignment" in names:
        raise MissingColumnsError("mag_accel_misalignment needs accelerometer columns "
                                  "(ax, ay, az), which the track lacks")
    base_names = tuple(n for n in names if n != "time_lag")
    fit_lag = "time_lag" in names
    if initial is not None and tuple(initial.model) == base_names and \
            getattr(initial, "inliers", None) is not None and \
            np.shape(initial.inliers) == (len(track.mag),):
        base = initial
    else:
        base = fit_core(track, model=base_names, kernel=kernel, tau=tau, initial=initial)
    t_g, w = gyro_rates(track)
    cov = {k: np.asarray(v, float) for k, v in track.covariates_at_mag().items()}
    m = np.asarray(track.mag, dtype=float)
    x = base.apply(m, cov)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    t = np.asarray(track.t_mag, dtype=float)
    f = np.flatnonzero(fresh(m))               # pairs use fresh samples only (indices into m)
    pairs = GyroPairs(x[f], t[f], base.K, t_g, w)
    inl = np.asarray(base.inliers, bool) if getattr(base, "inliers", None) is not None and \
        np.shape(base.inliers) == (len(m),) else np.ones(len(m), bool)
    sel = None
    if rows is not None:
        start = np.zeros(len(m), bool)
        start[np.asarray(rows)] = True
        sel = np.flatnonzero(start[f][pairs.a])
    p, lag, lm = fit_gyro_tied(pairs, fit_lag=fit_lag, kernel=kernel, inlier_samples=inl[f],
                           sel=sel, lag0=lag)
    r_pairs = pairs.residual(pairs.orientation(p), lag)
    rn_pairs = np.linalg.norm(r_pairs, axis=1)
    good = inl[f][pairs.a] & inl[f][pairs.b]
    width = width_from_residuals(kernel, rn_pairs[good] if good.any() else rn_pairs)
    at = f[pairs.a]
    r = np.zeros((len(m), 3))
    r[at] = r_pairs
    inliers = np.zeros(len(m), bool)
    inliers[at] = good & ((rn_pairs <= OUTLIER_WIDTHS * width) | (kernel == "l2"))
    rn = np.linalg.norm(r, axis=1)
    rms = float(np.sqrt(np.mean(rn[inliers] ** 2))) if inliers.any() else float("nan")
    weights = np.zeros(len(m))
    weights[at] = kernel_weights(kernel, rn_pairs, width)
    M = p[:9].reshape(3, 3)
    U, _, Vt = np.linalg.svd(M)
    rot = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    effects = dict(base.effects)
    if fit_lag:
        effects["time_lag"] = {"tau": float(lag)}
    cal = base.replace(model=names, effects=effects, rms=rms, n=len(m),
                       n_outliers=int((~inliers).sum()), inliers=inliers, weights=weights,
                       directions=x,
                       extra={**dict(base.extra or {}), "tau": width,
                              "gyro_tied": {"horizon_s": pairs.horizon,
                                            "gyro_map": [[float(v) for v in row] for row in M],
                                            "gyro_offset_rad_s": [float(v) for v in p[9:]]}})
    n_params = _n_base_params(base) + N_GYRO_PARAMS + int(fit_lag)
    return RegistrationFit(cal, r, x, inliers, rot, float("nan"), float(lag), n_params, rms,
                           status=lm.status, iterations=lm.iterations, message=lm.message)
