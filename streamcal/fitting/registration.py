"""Registration effects (docs/effects.md ``mag_accel_misalignment``, ``time_lag``) and their solver.

Parameters in a calibration file:

    "mag_accel_misalignment": {"rotation": [r1, r2, r3], "dip": δ}   rotation vector (rad) of the
        rotation R taking magnetometer-frame directions to the accelerometer frame; δ (rad) the
        constant angle between the field and the "down" direction ĝ.
    "time_lag": {"tau": τ}     seconds by which the magnetometer samples lag the IMU clock: the
        sample stamped t was taken at t − τ.

They do not change how a reading maps to a magnetometer-frame direction, so ``apply`` ignores
them; they matter when the direction is combined with accel/gyro.

Why a separate solver
---------------------
With a magnetometer alone every direction x_j is free on the sphere, so a frame rotation or a
lag leaves no trace in the ellipsoid residual. With the accelerometer the field keeps a constant
angle δ to gravity, which ties each direction to the gravity direction, leaving one free heading
per sample (the registration problem, solved by block coordinate descent as in the seed paper
"3-D asynchronous sensor registration", unit-norm subproblems). Precisely, with

    ĝ_j   unit gravity ("down") direction in the accelerometer frame at the magnetometer's true
          sampling instant t_j − τ (interpolated on the IMU rows),
    h_j   unit horizontal heading, h_j ⟂ ĝ_j (free, one angle per sample),
    R     rotation magnetometer → accelerometer frame (identity without the misalignment effect),
    δ     the dip: angle between field and down (δ_e = π/2 − δ is the inclination below the
          horizon, so x = R⁻¹(sin δ_e ĝ + cos δ_e h)),

the direction in the magnetometer frame is

    x_j = Rᵀ (cos δ ĝ_j + sin δ h_j)                                           (1)

and the reading ``m_j = K x_j + b + Σ_e f_e(θ_e, K x_j, c_j) + ε_j`` as in the ellipsoid model.
The residual r_j = K x_j + b + Σ f − m_j (sensor unit, (N,3)) is minimized robustly over the
global parameters p = (K, b, θ, R, δ, τ) and the headings:

  (a) headings given p — closed form per sample, vectorized: y_j = R K⁻¹(m_j − b − Σf) projected
      on the plane ⟂ ĝ_j and normalized (the point of the circle (1) nearest y_j), then two
      Gauss–Newton steps on the heading angle φ_j in sensor space (exact for anisotropic K);
  (b) p given the headings — one damped Gauss–Newton (Levenberg–Marquardt) step on the weighted
      residuals with analytic Jacobians (τ by a central difference). Plain alternation zig-zags
      (≈ 40 rounds, the headings and K, R, δ are strongly coupled), so the step is taken on the
      Schur complement of the 1×1 heading blocks: each sample's Jacobian row is projected off
      a_j = ∂r_j/∂φ_j, i.e. the headings follow p to first order, and (a) then re-solves them
      exactly. 4–8 rounds suffice. R is updated multiplicatively, R ← R exp([ε]×), ∂x/∂ε = [x]×;
  cost — Σ_j trust_j ρ̃(‖r_j‖²), trust_j the confidence in ĝ_j (below) and ρ̃(s) = ρ(min(s,
      (2w)²)) the fit's kernel ρ of width w capped at the 2 widths beyond which a sample is
      reported an outlier: an outlier adds a constant and exerts no pull. (Cauchy uncapped grows
      like log s: on BROAD 32, where a magnet stuck to the board puts a third of the samples
      ≈ 10 widths off, it pulled the ellipsoid onto them — K_zz 44 → 137 µT.) The step weights
      are w_j = trust_j ρ̃′. A trial step is accepted only when the cost itself does not rise.
  width — held fixed during a Levenberg–Marquardt pass (a width re-estimated every round makes
      the cost a moving target: it grew with the drift above), re-estimated from the median
      residual between passes until it moves < 5 % (as in :mod:`streamcal.fitting.autocal`).
      Whatever the passes did, the parameters returned never have a higher cost, at the final
      width, than the start.

τ is first located on a grid (the cost is not convex in τ beyond a fraction of the motion's
period) and then refined by (b).

The gravity direction ĝ and its trust come from :mod:`streamcal.fitting.gravity`.

Without the accelerometer, ``time_lag`` alone is estimated from the gyro: consecutive
directions are linked by the rotation rate (:mod:`streamcal.fitting.gyro_lag`, the gyro-tied
residual); :func:`registration_fit` hands such tracks over to it.

The rms reported (``Calibration.rms``) is sqrt(mean ‖r_j‖²) over inliers (‖r_j‖ ≤ 2 kernel
widths), the same statistic as the ellipsoid fit's, but of the gravity-tied residual (1): it is
compared with the gravity-tied fit *without* the registration effect, never with a free-direction
fit (whose residual cannot see these effects).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..calibration import Calibration, field_radius
from ..constants import HALF_NORMAL_MEDIAN, OUTLIER_WIDTHS
from ..errors import InputError, InsufficientDataError
from ..inputs.track import Track
from ..model.build import TERMS, build_effects, check_known, check_needs, terms_from_params
from ..model.catalog import REGISTRATION_EFFECTS
from .core import fit_core
from .damped_lm import damped_lm, lag_grid, search_lag, trimmed_cost
from .gravity import GravityReference, gravity_reference
from .registration_problem import LAG_STEP, _Problem  # noqa: F401  (LAG_STEP re-exported)
from .registration_result import RegistrationFit
from .result import FitResult
from .gyro_lag import gyro_lag_fit
from .kernels import WIDTH_KERNELS, kernel_weights, make_kernel, width_from_residuals

#: Grid of τ (s) searched before refining.
LAG_GRID = lag_grid(0.25)
LAG_GRID_SAMPLES = 1500
#: A fitted |τ| beyond this (s) means the data do not determine the lag (the grid spans ±0.25).
MAX_LAG = 0.3
MAX_ROUNDS = 40
RTOL = 1e-7
#: LM passes at a fixed kernel width (re-estimated between passes; settled when it moves less
#: than WIDTH_SETTLED, relative).
MAX_WIDTH_ROUNDS = 4
WIDTH_SETTLED = 0.05
#: Relative cost decrease that ends an LM pass while the width is still being estimated.
WIDTH_RTOL = 1e-3


# ---------------------------------------------------------------------------------- the fit


def _start(track, names, kernel, initial):
    """K, b and effect-term parameters to start from (a warm start or an ellipsoid fit)."""
    if initial is None:
        initial = fit_core(track, model=names, kernel=kernel)
    return initial


def registration_fit(track, model: Sequence[str], *, kernel: str = "cauchy",
                     tau: float | None = None, initial=None, rows: np.ndarray | None = None,
                     gref: GravityReference | None = None, max_rounds: int = MAX_ROUNDS,
                     rtol: float = RTOL) -> RegistrationFit:
    """Gravity-tied robust fit of ``model`` on ``track``'s magnetometer (see module docstring).

    ``model``: effect names; the registration effects in it are estimated, the others are fitted
    as usual (K, b, effect terms); without registration effects this is the gravity-tied fit
    with R = I and τ = 0 (only δ free), the base the registration effects are compared with.
    ``tau``: kernel width in sensor units (None: from the data). ``initial``: a Calibration to
    start from (else an ellipsoid fit of the non-registration part of the model). ``rows``:
    indices of the magnetometer samples to fit on (default all); the residuals, inliers and rms
    returned are still over every sample (headings re-solved there, step (a)). ``gref``: a precomputed
    :func:`gravity_reference`. ``rtol``: relative cost decrease that ends the last LM pass
    (a ranking fit may stop earlier than :data:`RTOL`).

    A track with a gyro but no accelerometer (and no ``mag_accel_misalignment`` in ``model``) is
    fitted on the gyro-tied residual instead (:func:`streamcal.fitting.gyro_lag.gyro_lag_fit`).
    """
    names = check_known(model)
    check_needs(names, track)
    if not track.has("accel") and track.has("gyro") and "mag_accel_misalignment" not in names:
        return gyro_lag_fit(track, names, kernel=kernel, tau=tau, initial=initial, rows=rows)
    base_names = tuple(n for n in names if n not in REGISTRATION_EFFECTS)
    fit_rot, fit_lag = "mag_accel_misalignment" in names, "time_lag" in names
    gref = gref if gref is not None else gravity_reference(track)
    start = _start(track, base_names, kernel, initial)
    m_all = np.asarray(track.mag, dtype=float)
    cov_all = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
    sel = np.arange(len(m_all)) if rows is None else np.asarray(rows)
    m = m_all[sel]
    cov = {k: v[sel] for k, v in cov_all.items()}
    terms = build_effects([n for n in names if n in TERMS], cov_all)
    known = {t.name: th for t, th in terms_from_params(start.effects)}
    thetas = [np.asarray(known.get(t.name, t.initial()), dtype=float)
              if t.name in known and len(known[t.name]) == t.n_params()
              else np.zeros(t.n_params()) for t in terms]
    reg = dict(start.effects)
    R = Rotation.from_rotvec(reg.get("mag_accel_misalignment", {}).get("rotation", np.zeros(3))
                             ).as_matrix() if fit_rot else np.eye(3)
    lag = float(reg.get("time_lag", {}).get("tau", 0.0)) if fit_lag else 0.0
    prob = _Problem(m, cov, gref, terms, fit_rot, fit_lag)
    K, b = np.array(start.K, dtype=float), np.array(start.b, dtype=float)

    if len(m) < 12:
        raise InsufficientDataError(f"{len(m)} magnetometer samples are too few for a "
                                    "gravity-tied fit")
    # δ from the data: median angle between the free-fit direction and down.
    g0, trust = prob.down(lag)
    y = (m - b) @ (R @ np.linalg.inv(K)).T
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    dip = reg.get("mag_accel_misalignment", {}).get("dip")
    if dip is None and not fit_rot and "mag_accel_misalignment" not in reg:
        dip = (start.extra or {}).get("dip")   # a gravity-tied start with R = I knows δ
    if dip is None:
        dip = np.median(np.arccos(np.clip(np.einsum("ni,ni->n", y, g0), -1, 1)))
    dip = float(dip)
    if fit_lag and "time_lag" not in reg:
        lag = _lag_grid(prob, K, b, thetas, R, dip)

    width_given = None if tau is None else float(tau)
    first = (K, b, thetas, R, dip, lag)
    h, r, trust = _evaluate(prob, first)
    rn_first = np.linalg.norm(r, axis=1)
    width = width_given or width_from_residuals(kernel, rn_first)
    state, budget, settled = first, max_rounds, width_given is not None
    for _ in range(MAX_WIDTH_ROUNDS):   # LM passes at a fixed width until the width settles
        # while the width is still moving a loose tolerance suffices (as in autocal)
        lm, cost, h, r = _refine(prob, state, kernel, width, budget,
                                 rtol if settled else max(rtol, WIDTH_RTOL))
        state = lm.x
        budget -= lm.iterations
        if settled or budget <= 0:
            break
        again = width_from_residuals(kernel, np.linalg.norm(r, axis=1))
        settled = abs(again - width) <= WIDTH_SETTLED * width
        width = again
    else:   # the width kept moving: polish at its last estimate
        lm, cost, h, r = _refine(prob, state, kernel, width, budget, rtol)
        state = lm.x
        budget -= lm.iterations
    status, message = lm.status, lm.message
    # The invariant: never return parameters whose robust cost (at the final width) is worse
    # than the start's (a width pass that moved away from a better start is undone).
    if not cost <= float(np.sum(trust * _loss(kernel, width).evaluate(rn_first ** 2)[0])):
        state = first
        h, r, _ = _evaluate(prob, first)
        message += "; the start was kept (the passes ended costlier at the final width)"
    K, b, thetas, R, dip, lag = state
    if fit_lag and abs(lag) > MAX_LAG:
        raise InsufficientDataError(f"the time lag is not determined by the data: the fit "
                                    f"wandered to {lag:.3f} s, beyond ±{MAX_LAG} s")
    if not np.all(np.isfinite(K)) or np.any(np.diag(K) <= 0):
        raise InsufficientDataError("the gravity-tied fit diverged: the data do not determine "
                                    "the registration")
    if len(m) < len(m_all):   # fitted on a subset: residuals, inliers and rms over every sample
        prob = _Problem(m_all, cov_all, gref, terms, fit_rot, fit_lag)
        h = prob.headings(K, b, thetas, R, dip, lag)
        r = prob.residual(K, b, thetas, R, dip, lag, h)
        m = m_all
    rn = np.linalg.norm(r, axis=1)
    width = width_given or width_from_residuals(kernel, rn)
    inliers = rn <= OUTLIER_WIDTHS * width if kernel != "l2" else np.ones(len(rn), bool)
    rms = float(np.sqrt(np.mean(rn[inliers] ** 2))) if inliers.any() else float("nan")
    g, _ = prob.down(lag)
    x, _ = prob.direction(R, dip, g, h)
    effects = {t.name: t.to_physical(th, 1.0) for t, th in zip(terms, thetas)}
    if fit_rot:
        effects["mag_accel_misalignment"] = {
            "rotation": [float(v) for v in Rotation.from_matrix(R).as_rotvec()], "dip": float(dip)}
    if fit_lag:
        effects["time_lag"] = {"tau": float(lag)}
    n_params = len(prob.pack(K, b, thetas, dip, lag))
    weights = kernel_weights(kernel, rn, width) * inliers   # the capped cost: no pull beyond
    cal = Calibration(K=K, b=b, sensor="mag", model=names, effects=effects, rms=rms, n=len(m),
                      n_outliers=int((~inliers).sum()), coverage=start.coverage,
                      unit=track.mag_unit, field=field_radius(K)
                      if track.mag_unit == "uT" else None, method="autocal", kernel=kernel,
                      inliers=inliers, weights=weights, directions=x,
                      extra={"noise_sigma": float(np.median(rn) / HALF_NORMAL_MEDIAN / np.sqrt(2)),
                             "tau": width, "dip": float(dip), "gravity": gref.method})
    return RegistrationFit(cal, r, x, inliers, R, float(dip), float(lag), n_params, rms,
                           status=status, iterations=max_rounds - budget, message=message)


@dataclass(frozen=True)
class _Capped:
    """ρ̃(s) = ρ(min(s, cap)) of the wrapped kernel (module docstring, "cost"); concave in s when
    ρ is, so a step lowering the weighted sum of squares lowers Σ ρ̃ too."""

    kernel: object
    cap: float

    def evaluate(self, s):
        s = np.asarray(s, dtype=float)
        rho, d1, d2 = self.kernel.evaluate(np.minimum(s, self.cap))
        inside = s <= self.cap
        return rho, np.where(inside, d1, 0.0), np.where(inside, d2, 0.0)


def _loss(kernel: str, width: float):
    """The fit's kernel of ``width`` (sensor unit) capped at :data:`OUTLIER_WIDTHS` widths."""

    if kernel not in WIDTH_KERNELS:
        return make_kernel(kernel)
    return _Capped(make_kernel(kernel, width), (OUTLIER_WIDTHS * width) ** 2)


def _evaluate(prob: "_Problem", state: tuple):
    """(headings (N,3), residuals (N,3), trust (N,)) at ``state`` = (K, b, θ, R, δ, τ)."""
    h = prob.headings(*state)
    return h, prob.residual(*state, h), prob.down(state[5])[1]


def _refine(prob: "_Problem", state: tuple, kernel: str, width: float, max_rounds: int,
            rtol: float = RTOL) -> tuple:
    """One LM pass at a fixed ``width`` → (:class:`~.damped_lm.LMStatus` whose ``x`` is never
    costlier than ``state``, its cost Σ trust ρ̃, headings (N,3), residuals (N,3))."""
    loss = _loss(kernel, width)

    def cost_at(st):
        h, r, trust = _evaluate(prob, st)
        rho, d1, _ = loss.evaluate(np.sum(r * r, axis=1))
        cost = float(np.sum(trust * rho))
        return (cost if np.isfinite(cost) else np.inf), trust * d1, h, r

    def linearize(st, aux):
        cost, w, h, r = aux
        H, grad = prob.reduced_normal(*st, h, r, w)
        return cost, H, grad, None

    def propose(st, d):
        K, b, thetas, R, dip, lag = st
        return prob.unpack(prob.pack(K, b, thetas, dip, lag) + d, R, lag)

    def evaluate(st, _ctx):
        aux = cost_at(st)
        return aux[0], aux

    aux = cost_at(state)
    res = damped_lm(state, aux, aux[0], linearize=linearize, propose=propose,
                    evaluate=evaluate, max_iter=max_rounds, rtol=rtol)
    cost, _, h, r = res.aux
    return res, cost, h, r


def _lag_grid(prob, K, b, thetas, R, dip) -> float:
    """τ (s) minimizing the trimmed gravity-tied cost over :data:`LAG_GRID` (on at most
    :data:`LAG_GRID_SAMPLES` evenly strided samples)."""
    step = max(1, len(prob.m) // LAG_GRID_SAMPLES)
    idx = np.arange(0, len(prob.m), step)
    prob = _Problem(prob.m[idx], {k: v[idx] for k, v in prob.cov.items()}, prob.gref,
                    prob.terms, prob.fit_rot, prob.fit_lag)

    def cost_at(lag):
        h = prob.headings(K, b, thetas, R, dip, lag, gn_steps=1)
        rn = np.linalg.norm(prob.residual(K, b, thetas, R, dip, lag, h), axis=1)
        return trimmed_cost(rn, prob.down(lag)[1])

    return search_lag(LAG_GRID, cost_at)[0]


def fit_with_registration(track, model: Sequence[str] = ("hard_iron", "soft_iron",
                                                          "mag_accel_misalignment"), *,
                          kernel: str = "cauchy", tau: float | None = None, sensor: str = "mag",
                          initial=None, full_output: bool = False):
    """Calibrate ``track``'s magnetometer with the registration effects in ``model`` (and any
    other catalog effects) by the gravity-tied fit of the module docstring → :class:`Calibration`
    whose ``effects`` hold ``{"mag_accel_misalignment": {"rotation": [rx, ry, rz] rad, "dip":
    rad}}`` and/or ``{"time_lag": {"tau": s}}``; ``rms`` is the gravity-tied residual (µT).
    Without accelerometer columns, ``time_lag`` comes from the gyro and ``rms`` is the gyro-tied
    residual (:mod:`streamcal.fitting.gyro_lag`). ``full_output``: a
    :class:`~streamcal.fitting.result.FitResult` instead (the calibration and the solver status)."""
    if sensor != "mag":
        raise InputError(f"registration effects apply to the magnetometer, not --sensor {sensor}")
    if not isinstance(track, Track):
        raise InputError("registration effects need a track with accelerometer (or, for "
                         "time_lag, gyroscope) columns, not an array of readings")
    res = registration_fit(track, model, kernel=kernel, tau=tau, initial=initial)
    if full_output:
        return FitResult(res.calibration, res.status, res.iterations, res.message)
    return res.calibration
