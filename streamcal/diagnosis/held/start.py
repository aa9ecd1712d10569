"""The *held* starting point of a diagnosis: a calibration the user already holds (or a stated
default), re-estimated only where the recording determines it.

Flights, drives and warm-ups cover a slice of the sphere, which cannot determine a fresh K and
b. The parameters the slice determines (:func:`streamcal.diagnosis.held.choose_free`, a
Cramér–Rao error below a tolerance) are re-estimated, the others held at the calibration's
values; a candidate effect is fitted the same way (held parameters stay held, the effect's θ is
free). Without a calibration the held values are a stated default: b from an algebraic sphere
fit re-estimated on the slice, K = r·I with r = median ‖m − b‖; b must then be determined
(refused otherwise, saying how many samples at this noise would do).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ...calibration import DEFAULT_MODEL, Calibration
from ...errors import InputError, InsufficientDataError, StreamcalError
from ...fitting.entries import B_PARAMS, RADIUS
from ...fitting.outlier_rule import outlier_mask, residual_width
from ...model import REGISTRATION_EFFECTS, build_effects, terms_from_params
from ...model.build import check_known
from .gyro_pin import confirm, gyro_pin, pinned_model
from .fit import (TOLERANCE, HeldFit, choose_free, core_params, field_radius, held_fit,
                  radius_free)
from .recheck import check, settle
from .reference_rows import frame
from ..noise import noise_floor

#: Fewest samples for any diagnosis against a calibration.
MIN_SAMPLES = 30
#: Default-calibration iterations (b on the slice, then r from it).
DEFAULT_ROUNDS = 3
#: The radius fitted on each half of a recording agrees within this many σ of the difference
#: when an added effect releases it.
STABLE_SIGMAS = 3.0


class HeldEval:
    """One held fit as an evaluation of :mod:`streamcal.diagnosis.story`: residuals (N,3), the
    one outlier rule's inliers (N,) over the times ``t`` (N,) s, the number of free
    parameters ``p``, the estimated core parameters ``free``."""

    def __init__(self, fit: HeldFit, cal: Calibration, p: int, terms=(), t=None, free=()):
        self.fit, self.p, self.terms, self.free = fit, p, list(terms), list(free)
        self.r, self.x, self.s, self.normal = fit.r, fit.x, fit.s, fit.normal
        self.rss = np.sum(fit.r ** 2, axis=1)
        # the width from this model's own residual, as a fresh fit takes it (not the noise
        # floor the held fit weighs with: a misfit larger than the noise is not an outlier)
        self.inliers = ~outlier_mask(np.sqrt(self.rss), residual_width(np.sqrt(self.rss)), t)
        self.rms = float(np.sqrt(np.mean(self.rss[self.inliers]))) if self.inliers.any() \
            else float("nan")
        self.cal = cal.replace(inliers=self.inliers, n_outliers=int((~self.inliers).sum()),
                               rms=self.rms, n=len(self.rss))


def default_calibration(m: np.ndarray, model: Sequence[str] = DEFAULT_MODEL) -> Calibration:
    """The stated default: b from the algebraic sphere fit ‖m‖² = 2 mᵀb + c, K = r·I with
    r = median ‖m − b‖ (sensor unit)."""
    A = np.column_stack([2 * m, np.ones(len(m))])
    sol, *_ = np.linalg.lstsq(A, np.sum(m * m, axis=1), rcond=None)
    b = sol[:3]
    r = float(np.median(np.linalg.norm(m - b, axis=1)))
    return Calibration(K=r * np.eye(3), b=b, model=tuple(model), method="default")


def _calibration(K, b, base: Calibration, terms, fit: HeldFit, model,
                 reference=None) -> Calibration:
    effects = dict(base.effects)
    for term, theta in terms:
        effects[term.name] = term.to_physical(theta, 1.0)
    # the field strength follows the radius, so that the corrected field's matrix keeps its scale
    field = None if base.field is None else float(base.field) * fit.scale
    # fitted against the attitude reference, the frame follows K (reference_rows.frame)
    turned = {} if reference is None else {"frame_rotation_Q": frame(K, reference.V).tolist()}
    return base.replace(K=K, b=b, model=tuple(model), effects=effects, inliers=fit.inliers,
                        weights=None, directions=fit.x, field=field,
                        extra={**dict(base.extra or {}), "tau": fit.tau, **turned})


#: Ridge of :func:`linear_start`, relative to each column's sum of squares.
RIDGE = 1e-2


def linear_start(term, s: np.ndarray, normal: np.ndarray, u: np.ndarray, cov,
                 tau: float) -> np.ndarray:
    """Starting θ for a candidate: least squares of the signed normal residual ``s`` (N,) on a
    constant and the columns nᵀ ∂f/∂θ (the effect's first-order change of s is −nᵀ ∂f/∂θ δθ),
    kept only when it lowers the linearised Cauchy cost (width ``tau``); else ``term.initial()``.

    Why: an effect of a few µT against a noise of 0.1 µT puts the samples it moves (the flight
    against the ground run, full throttle) beyond the Cauchy width, where their weight is
    ~(τ/s)²; a robust fit started at θ = 0 then calls them outliers and never explains them."""
    theta0 = np.asarray(term.initial(), float)
    Z = np.einsum("ni,nip->np", normal, term.jac_theta(theta0, u, cov))
    ok = np.all(np.isfinite(Z), axis=1) & np.isfinite(s)
    if ok.sum() <= Z.shape[1] + 1:
        return theta0
    A = np.column_stack([np.ones(int(ok.sum())), Z[ok]])
    # a light ridge: channels that move together (throttle, motor outputs) would otherwise get
    # large cancelling coefficients, far outside where the linearisation holds
    H = A.T @ A
    H[1:, 1:] += RIDGE * np.diag(np.diag(H[1:, 1:]) + 1e-300)
    coef = np.linalg.solve(H, A.T @ s[ok])
    after = s[ok] - coef[0] - Z[ok] @ coef[1:]
    if np.sum(np.log1p((after / tau) ** 2)) < np.sum(np.log1p((s[ok] / tau) ** 2)):
        return theta0 + coef[1:]
    return theta0


def _refuse_b(n: int, errors: dict, tol: float, unit: str, sigma: float) -> None:
    from ...units import display_unit

    unit = display_unit(unit)
    worst = max(errors.get(name, np.inf) for name, _ in B_PARAMS)
    if worst <= tol:
        return
    need = int(np.ceil(n * (worst / tol) ** 2)) if np.isfinite(worst) else None
    more = (f"about {need} samples at this noise ({sigma:.3g} {unit} per axis), " if need else "")
    raise InsufficientDataError(
        f"without a calibration the hard-iron offset b must come from this recording, but its "
        f"{n} samples predict it to ±{worst:.3g} {unit} (Cramér–Rao, noise {sigma:.3g} {unit}), "
        f"above the tolerance {tol:.3g} {unit} ({TOLERANCE:.1%} of the field radius). What "
        f"would answer it: {more}a wider range of directions, or a calibration you already "
        f"hold (--cal CAL.json)")


class HeldStart:
    """The base model of a held diagnosis and the way to fit any model on top of it.

    ``track``: the recording; ``calibration``: the one held (None: the stated default of
    :func:`default_calibration` for ``model``); ``tolerance``: a parameter is re-estimated when
    its predicted error is below ``tolerance`` × the field radius. Refuses
    (InsufficientDataError) with fewer than :data:`MIN_SAMPLES` samples or, without a
    calibration, when b cannot be determined to that tolerance.

    After construction: ``base`` (:class:`HeldEval` of the diagnosed model on every sample),
    ``model``, ``free`` and ``held_terms`` (what is re-estimated / the calibration's effects,
    held), ``source``, ``nf`` (the noise floor estimate), ``settled``, ``pin``, ``errors``
    (Cramér–Rao errors at the start), ``tol`` (sensor unit), ``reference`` (the
    :class:`~.reference_rows.ReferenceRows` given, scaled to the field radius; None without).

    ``reference``: the attitude reference's samples (:func:`.reference_rows.reference_rows`):
    every fit and every Cramér–Rao choice then uses its direction residual beside the
    magnitude's."""

    def __init__(self, track, calibration: Calibration | None = None, *,
                 model: Sequence[str] = DEFAULT_MODEL, calibration_source: str | None = None,
                 tolerance: float = TOLERANCE, reference=None):
        m = np.asarray(track.mag, dtype=float)
        n = len(m)
        self.track, self.m, self.unit = track, m, track.mag_unit
        if n < MIN_SAMPLES:
            raise InsufficientDataError(f"{n} samples are too few to diagnose anything: at "
                                        f"least {MIN_SAMPLES} are needed (record longer)")
        self.t = t = np.asarray(track.t_mag, dtype=float)
        cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
        cov.setdefault("t", t)
        self.cov = cov
        self.gyro = np.stack([cov[k] for k in ("gx", "gy", "gz")], 1) if all(
            k in cov for k in ("gx", "gy", "gz")) else None
        self.nf = nf = noise_floor(m, t, self.gyro)
        sigma = float(np.sqrt(np.mean(np.square(nf.sigma_axes)))) if np.all(
            np.isfinite(nf.sigma_axes)) and np.any(nf.sigma_axes > 0) else float("nan")
        self.given = given = calibration is not None
        if given:
            if calibration.sensor != "mag":
                raise InputError(f"{calibration_source or 'calibration'}: a "
                                 f"{calibration.sensor} calibration cannot diagnose "
                                 "magnetometer readings")
            base_cal = calibration
            model = tuple(n_ for n_ in calibration.model if n_ not in REGISTRATION_EFFECTS)
            self.source = (calibration_source or dict(calibration.extra or {}).get("source")
                           or "given calibration")
        else:
            model = tuple(check_known(model))
            base_cal = default_calibration(m, model)
            self.source = ("default: b re-estimated from this recording, K = r·I with "
                           "r = median |m − b|")
        self.model = model
        self.held_terms = held_terms = terms_from_params(base_cal.effects)
        self.names = names = core_params(model)
        K0, b0 = base_cal.K, base_cal.b
        tol = tolerance * field_radius(K0)
        if not np.isfinite(sigma) or sigma <= 0:
            sigma = float(np.median(np.abs(np.linalg.norm(m - b0, axis=1) - field_radius(K0))))
        b_names = [p for p, _ in B_PARAMS]
        keep = () if given else b_names   # without a calibration b is what is asked for
        ref = None if reference is None else reference.scaled(field_radius(K0))
        free, errors = choose_free(names, K0, b0, m, cov, held_terms, sigma, tol, keep, ref)
        if not given:
            _refuse_b(n, errors, tol, self.unit, sigma)
            for _ in range(DEFAULT_ROUNDS):   # b on the slice, r from it
                fit = held_fit(m, cov, K0, b0, b_names, held_terms, reference=ref)
                b0 = fit.b
                K0 = float(np.median(np.linalg.norm(m - b0, axis=1))) * np.eye(3)
                ref = None if ref is None else ref.scaled(field_radius(K0))
            base_cal = base_cal.replace(K=K0, b=b0)
            tol = tolerance * field_radius(K0)
            free, errors = choose_free(names, K0, b0, m, cov, held_terms, sigma, tol, keep, ref)
            _refuse_b(n, errors, tol, self.unit, sigma)
        # re-check at the fitted point; the candidates then use the settled estimated set
        settled = settle(lambda f: held_fit(m, cov, K0, b0, f, held_terms, (), sigma, ref), free,
                         m, cov, held_terms, sigma, tol, field_radius(K0), b0, keep, ref)
        free, fit = settled.free, settled.fit
        # then the field strength, at the fitted point, over what was settled
        add_radius, errors[RADIUS] = radius_free(free, fit.K, fit.b, m, cov, held_terms, sigma,
                                                 tol, ref)
        if add_radius:   # kept only when nothing estimated without it has to be held
            with_radius = settle(lambda f: held_fit(m, cov, K0, b0, f, held_terms, (), sigma,
                                                    ref),
                                 [*free, RADIUS], m, cov, held_terms, sigma, tol,
                                 field_radius(K0), b0, keep, ref)
            if set(with_radius.free) == {*free, RADIUS}:
                settled, free, fit = with_radius, with_radius.free, with_radius.fit
        # held parameters the gyro link determines (only when that helps: gyro_pin's rules)
        pin = gyro_pin(track, m, t, cov, held_terms, fit, [p for p in free if p != RADIUS],
                       [p for p in names if p not in free], tol, field_radius(K0))
        K0p, b0p = pinned_model(K0, b0, pin)
        again = confirm(pin, fit, lambda: settle(
            lambda f: held_fit(m, cov, K0p, b0p, f, held_terms, (), sigma, ref), free, m, cov,
            held_terms, sigma, tol, field_radius(K0), b0, keep, ref))
        if again is not None:
            K0, b0, settled, free, fit = K0p, b0p, again, again.free, again.fit
        self.K0, self.b0, self.sigma, self.tol, self.errors = K0, b0, sigma, tol, errors
        self.free, self.settled, self.pin, self.base_cal = free, settled, pin, base_cal
        self.reference = ref
        if np.isfinite(errors[RADIUS]):   # considered: the diagonal was not all estimated
            self.names = [*names, RADIUS]
        self.radius = field_radius(K0)
        self.base = HeldEval(fit, _calibration(fit.K, fit.b, base_cal, [], fit, model, ref),
                             len(free), [], t, free)

    def cov_at(self, rows=None) -> dict:
        """The covariates (N,) at every sample, or at the sample indices ``rows`` (the ranking
        subsample: taken once, every candidate refit reuses them)."""
        if rows is None:
            return self.cov
        if getattr(self, "_rows", None) is not rows:
            self._rows, self._cov_rows = rows, {k: v[rows] for k, v in self.cov.items()}
        return self._cov_rows

    def _at(self, rows=None) -> tuple:
        """(readings (M,3), covariates, times (M,) s, attitude reference or None) of every
        sample, or of the sample indices ``rows``."""
        if rows is None:
            return self.m, self.cov, self.t, self.reference
        ref = None if self.reference is None else self.reference.at(rows)
        return self.m[rows], self.cov_at(rows), self.t[rows], ref

    def evaluate(self, new_terms, start: HeldEval | None = None, rows=None,
                 free: Sequence[str] | None = None) -> HeldEval:
        """Fit the base model plus ``new_terms`` (``[(term, θ start), …]``) from ``start``'s
        K, b (default the held values) on every sample, or on the sample indices ``rows``,
        estimating ``free`` (default ``start``'s, else the base's)."""
        m, cov, t, ref = self._at(rows)
        K_s, b_s = (self.K0, self.b0) if start is None else (start.fit.K, start.fit.b)
        free = list(free if free is not None else start.free if start is not None else self.free)
        fit = held_fit(m, cov, K_s, b_s, free, self.held_terms, new_terms, self.sigma, ref)
        if start is not None:     # K_s carries start's radius already
            fit.scale *= start.fit.scale
        terms = [term for term, _ in new_terms]
        cal = _calibration(fit.K, fit.b, self.base_cal, list(zip(terms, fit.thetas)), fit,
                           (*self.model, *(term.name for term in terms)), self.reference)
        return HeldEval(fit, cal, len(free) + sum(len(th) for th in fit.thetas), terms, t, free)

    def add(self, name: str, ref: HeldEval, rows=None) -> HeldEval:
        """``ref``'s model plus the effect ``name``, started where a linear fit of ``ref``'s
        residual puts it (:func:`linear_start`), on every sample or on ``rows``."""
        cov = self.cov_at(rows)
        term = build_effects([name], cov)[0]
        prior = list(zip(ref.terms, ref.fit.thetas))
        start = linear_start(term, ref.s, ref.normal, ref.x @ ref.fit.K.T, cov, ref.fit.tau)
        ev = self.evaluate([*prior, (term, start)], ref, rows)
        if np.any(start != term.initial()) and not ev.rms <= ref.rms * 10:
            ev = self.evaluate([*prior, (term, term.initial())], ref, rows)
        return self._with_radius(ev, rows)

    def _with_radius(self, ev: HeldEval, rows) -> HeldEval:
        """``ev`` with the field radius estimated too, when the base held it but the model
        with ``ev``'s effects determines it: an effect the base lacked (a motor field) can be
        what left it undetermined. Three conditions: its predicted error (:func:`radius_free`),
        the re-check at the fitted point (:func:`streamcal.diagnosis.held.recheck.check`) of
        every estimated parameter, and the same radius, determined, from each half of the
        samples in time: a field strength is one number for the recording, and a model that
        leaves much unexplained can drift along it on one half."""
        if RADIUS in ev.free or RADIUS not in self.names or not np.isfinite(ev.rms):
            return ev
        m, cov, _, ref = self._at(rows)
        terms = [*self.held_terms, *zip(ev.terms, ev.fit.thetas)]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            ok, _ = radius_free(ev.free, ev.fit.K, ev.fit.b, m, cov, terms, self.sigma,
                                self.tol, ref)
        if not ok:
            return ev
        prior = list(zip(ev.terms, ev.fit.thetas))
        free = [*ev.free, RADIUS]
        # a fit drifting along an undetermined direction overflows on its way (as in settle)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            trial = self.evaluate(prior, ev, rows, free)
            failed = check(trial.fit, trial.free, m, cov, [*self.held_terms,
                           *zip(trial.terms, trial.fit.thetas)], self.sigma, self.tol,
                           self.radius, self.b0, ref)
        if failed or not self._same_on_each_half(prior, ev, rows, free):
            return ev
        return trial

    def _same_on_each_half(self, prior, ev: HeldEval, rows, free) -> bool:
        """Whether the model ``prior`` estimating ``free`` (with the radius), started at
        ``ev``, determines the radius on each half in time of the samples (``rows``, None: all;
        its error within √2 × the tolerance) and gives both the same within
        :data:`STABLE_SIGMAS` σ of the difference."""
        idx = np.arange(len(self.m)) if rows is None else np.asarray(rows)
        idx = idx[np.argsort(self.t[idx], kind="stable")]
        values = []
        for half in (idx[:len(idx) // 2], idx[len(idx) // 2:]):
            try:
                with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                    fit = self.evaluate(prior, ev, half, free).fit
            except (StreamcalError, np.linalg.LinAlgError, ValueError):
                return False
            values.append(fit.estimated.get(RADIUS, (np.nan, np.inf)))
        (a, sa), (b, sb) = values
        # half the samples: the tolerance on the error × √2
        return bool(np.isfinite([a, b, sa, sb]).all() and max(sa, sb) <= np.sqrt(2) * self.tol
                    and abs(a - b) <= STABLE_SIGMAS * np.hypot(sa, sb))
