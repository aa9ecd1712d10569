"""Ranking the effects the model may be missing.

Each candidate effect is *actually refitted* (the same fitter as the base model), so its
``rms_after`` is what "add it and refit" gives. Significance: on the samples that both fits call
inliers, with ``RSS = Σ‖r_j‖²`` of the eq. 41 residuals (one degree of freedom per sample: the
direction takes the other two), the nested-model F statistic

    F = ((RSS₀ − RSS₁) / P) / (RSS₁ / (n − p₁)),     P added parameters, p₁ all global ones

is referred to F(P, n − p₁). With thousands of samples a physically negligible effect is still
"significant", so an effect is only called missing when it is also material (the rms drops by
at least :data:`MIN_DROP`) and the base rms is clearly above the noise floor of its residual
(:data:`ABOVE_FLOOR`; the magnetometer's for the sensor residual, a tied residual's own,
:mod:`streamcal.diagnosis.tied_noise`, for the registration effects): a clean track must come
out ``at_noise_floor``.

Registration effects (``mag_accel_misalignment``, ``time_lag``) leave no trace in the eq. 41
residual (every direction is free), so they are judged on the gravity-tied residual of
:mod:`streamcal.fitting.registration` instead: the candidate's refit is compared — same F test,
same materiality rule — with the gravity-tied fit of the current model *without* the effect.
Both rms values are sqrt(mean ‖r_j‖²) over each fit's inliers in the sensor unit, computed the
same way, and "add the effect and refit" returns exactly the promised ``rms_after``; but that
scale includes the error of the gravity reference, so it is compared with the tied base (given
in the evidence text), not with the diagnosis' free-direction ``rms``. Candidates are ranked by
``rms_after`` / the rms each was compared with.

On a track with a gyro but no accelerometer, ``time_lag`` is judged the same way on the
gyro-tied residual of :mod:`streamcal.fitting.gyro_lag` (the reading predicted from the sample
0.5 s earlier carried over by the integrated gyro, sensor unit): base and candidate are the
gyro-tied fits without and with τ (same pairs, same 12 gyro-map parameters), so rms and
rms_after are again the same statistic, and ``streamcal fit --add time_lag`` on that track
returns the promised rms. Its evidence says what was measured ("gyro-tied rms 1.56 → 0.82 µT;
direction changes lag the gyro by 30.0 ms"). Overlapping pairs make neighbouring residuals
correlated; so do a slowly varying misfit and the smooth linear accelerations in the gravity
reference. The F test therefore counts samples by their effective number (:func:`effective_n`,
the AR(1) rule on the larger model's residuals in time order) rather than one per sample, and
the materiality rule still guards a clean track. With an accelerometer the gravity-tied candidate is kept (it is what ``fit`` refits) and
its evidence adds what the gyro alone says.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from ..values import fields_equal
from ..model.catalog import CORE_EFFECTS
from ..model.registry import declaration

P_VALUE = 1e-6
MIN_DROP = 0.10
ABOVE_FLOOR = 1.10
#: Global parameters of the core models (their declarations' ``n_params``).
CORE_PARAMS = {name: int(declaration(name).n_params) for name in CORE_EFFECTS}


@dataclass(frozen=True, eq=False)
class Candidate:
    """One effect tried on top of a model: a value (:func:`dataclasses.replace` derives a
    changed one). Equal when the fields a diagnosis' JSON carries are
    (:func:`streamcal.values.same`: NaN equal to NaN): ``n_params``, the refit ``calibration``
    and the engine's fitted models (``_evaluated``, ``_reference``) take no part in equality
    and are not saved (``n_params`` is 0 after :meth:`from_dict`)."""

    effect: str
    rms_after: float
    p_value: float
    evidence: str
    #: Parameters the effect adds to the model it extends (not in the JSON, not compared).
    n_params: int = field(default=0, compare=False)
    #: Both tests of :func:`tests` pass: the effect is called missing (the JSON gives them apart,
    #: ``significant`` the F test and ``material`` the drop).
    significant: bool = False
    calibration: object = field(default=None, repr=False, compare=False)
    #: The residual family ``rms_after`` is on ("sensor", "gravity_tied", "gyro_tied") and the
    #: rms of the model without the effect on that same residual (None: the diagnosis' rms).
    residual: str = "sensor"
    rms_before: float | None = None
    #: Samples ``rms_before`` and ``rms_after`` are over: those that are not outliers of the
    #: model with the effect (for an effect the ladder adds, the ladder's samples).
    n: int = 0
    #: Why the fitted effect is physically implausible (then neither significant nor material).
    implausible: str = ""
    _evaluated: object = field(default=None, repr=False, compare=False)
    _reference: object = field(default=None, repr=False, compare=False)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Candidate):
            return NotImplemented
        return fields_equal(self, other)

    __hash__ = None   # equal values need not share a hash: they hold floats compared NaN-safe

    def replace(self, **changes) -> "Candidate":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return {"effect": self.effect, "rms_after": self.rms_after, "p_value": self.p_value,
                "evidence": self.evidence, "n": int(self.n)}

    @classmethod
    def from_dict(cls, d: dict) -> "Candidate":
        """A candidate from its JSON (a diagnosis' ``candidates`` entry); null numbers → NaN.
        The JSON's ``significant`` is the F test alone; ``significant`` here is that test and
        ``material`` both (:func:`is_significant`)."""
        def num(key):
            v = d.get(key)
            return float("nan") if v is None else float(v)

        return cls(effect=d["effect"], rms_after=num("rms_after"), p_value=num("p_value"),
                   evidence=d.get("evidence", ""),
                   significant=bool(d.get("significant", False) and d.get("material", True)),
                   residual=d.get("residual", "sensor"),
                   rms_before=None if d.get("rms_before") is None else float(d["rms_before"]),
                   n=int(d.get("n", 0)), implausible=d.get("implausible", ""))


def n_global_params(cal) -> int:
    from ..model import terms_from_params

    core = sum(CORE_PARAMS[n] for n in cal.model if n in CORE_PARAMS)
    core = min(core, 9)  # scale ⊂ soft_iron
    return core + sum(t.n_params() for t, _ in terms_from_params(cal.effects))


def effective_n(r: np.ndarray) -> float:
    """Independent samples worth of the residuals ``r`` (n,3), in time order: the AR(1) rule
    n (1 − ρ)/(1 + ρ) with ρ the lag-1 autocorrelation (mean over the axes, clipped to
    [0, 0.999]). White residuals give n; a slowly varying misfit or the overlapping windows of
    the gyro-tied pairs give far fewer."""
    r = np.asarray(r, dtype=float)
    n = len(r)
    if n < 3:
        return float(n)
    d = r - r.mean(axis=0)
    num = np.sum(d[1:] * d[:-1], axis=0)
    den = np.sum(d * d, axis=0)
    ok = den > 0
    rho = float(np.clip(np.mean(num[ok] / den[ok]), 0.0, 0.999)) if ok.any() else 0.0
    return n * (1.0 - rho) / (1.0 + rho)


def f_test(rss0: float, rss1: float, p_added: int, n: float, p1: int) -> float:
    """p-value of the nested-model F test (see module docstring); ``n`` may be an effective
    sample count (:func:`effective_n`), which scales the statistic's denominator degrees."""
    dof = max(n - p1, 1)
    if rss1 <= 0 or p_added <= 0:
        return 0.0 if rss0 > rss1 else 1.0
    F = max(rss0 - rss1, 0.0) / p_added / (rss1 / dof)
    return float(np.exp(scipy.stats.f.logsf(F, p_added, dof)))


def tests(rms: float, rms_after: float, p_value: float, floor: float) -> tuple[bool, bool]:
    """``(significant, material)``: p < :data:`P_VALUE`; the rms drops by at least
    :data:`MIN_DROP` and (with a measured ``floor``, NaN when not) is above
    :data:`ABOVE_FLOOR` × the floor."""
    above = not np.isfinite(floor) or rms > ABOVE_FLOOR * floor
    return bool(p_value < P_VALUE), bool(rms_after <= (1 - MIN_DROP) * rms and above)


def is_significant(rms: float, rms_after: float, p_value: float, floor: float) -> bool:
    """Both :func:`tests` pass (the effect is called missing)."""
    return all(tests(rms, rms_after, p_value, floor))


def evidence(effect: str, term, s: np.ndarray, normal: np.ndarray, u: np.ndarray, cov,
             inliers: np.ndarray) -> str:
    """Sentence with the multiple correlation between the signed residual ``s`` (N,) and the
    normal component of the effect's term direction ``nᵀ ∂f/∂θ`` (N,P) — the score test's view
    of how much of the residual the effect could explain; what the residual follows is the
    effect's declared ``subject``."""
    if term is None:
        return ""
    theta = term.initial()
    Z = np.einsum("ni,nip->np", normal, term.jac_theta(theta, u, cov))[inliers]
    y = s[inliers]
    A = np.column_stack([np.ones(len(y)), Z])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    sst = np.sum((y - y.mean()) ** 2)
    r = float(np.sqrt(max(0.0, 1 - np.sum((y - A @ coef) ** 2) / sst))) if sst > 0 else 0.0
    subject = declaration(effect).evidence_subject(term)
    return f"residual follows {subject} (r={r:.2f})"


def registration_evidence(effect: str, rms_before: float, rms_after: float, cal, unit: str,
                          kind: str = "gravity") -> str:
    """Sentence for a registration candidate: the tied rms (``kind`` "gravity" or "gyro") it is
    compared with (the fit without the effect) and what the refit found (the effect's declared
    ``tied_evidence``)."""
    from ..units import display_unit

    text = f"{kind}-tied rms {rms_before:.3g} → {rms_after:.3g} {display_unit(unit)}"
    params = cal.effects.get(effect, {}) if cal is not None else {}
    detail = declaration(effect).tied_evidence
    return text + (detail(params, kind) if detail is not None else "")
