"""The verdict of a diagnosis (docs/cli.md ``verdict``) and the rules it states.

Three verdicts:

- ``effect_missing``: the best catalog effect is both significant and material
  (:func:`significance_rule` says both tests with their numbers);
- ``at_noise_floor``: no such effect, the noise floor of the residual the rms is on is measurable
  and the rms is within :data:`FLOOR_FACTOR` of it — the magnetometer's floor
  (:mod:`streamcal.diagnosis.noise`) for the sensor residual, the tied residual's own floor
  (:mod:`streamcal.diagnosis.tied_noise`: the magnetometer's noise it keeps and its reference's
  error) for a model judged on a gravity- or gyro-tied residual;
- ``unexplained``: anything else — the rms is clearly above the floor, or the floor cannot be
  measured — with no catalog effect explaining it. The diagnosis then says where the misfit
  sits (:mod:`streamcal.diagnosis.misfit`).
"""
from __future__ import annotations

import numpy as np

from . import candidates as cand

#: ``at_noise_floor`` only while rms ≤ FLOOR_FACTOR × the floor. Clean simulated tracks give
#: 0.9–1.3 (tests/test_diagnose.py), the real tiva MPU-9250 recordings 2.2–3.9.
FLOOR_FACTOR = 1.5
#: A noise estimate more than this many times the fit's sensor-residual rms is not the noise (a
#: fit keeps about the noise in its residual; clean tracks give floor/rms 0.8–1.3).
FLOOR_OVER_RMS_MAX = 1.5


#: What a tied residual's own floor holds, in words.
TIED_FLOOR_OF = {
    "gravity_tied": ("the gravity-tied residual's own floor (the magnetometer noise it keeps and "
                     "the error of the accelerometer's gravity direction from the motion and "
                     "noise it sees)"),
    "gyro_tied": ("the gyro-tied residual's own floor (the magnetometer noise of both samples "
                  "of a pair and the gyro's noise between them)"),
}


def floor_rule(residual: str = "sensor", factor: float = FLOOR_FACTOR) -> str:
    """The ``at_noise_floor`` rule in words (``noise_floor_rule``) for a model whose rms is on
    ``residual``: which floor governs."""
    if residual in TIED_FLOOR_OF:
        label = residual.replace("_", "-")
        return (f"at_noise_floor only when {TIED_FLOOR_OF[residual]} is measurable and the "
                f"{label} rms is at most {factor:g}× that floor")
    return (f"at_noise_floor only when the noise floor is measurable and the sensor-residual "
            f"rms is at most {factor:g}× the floor")


def significance_rule() -> str:
    """Both tests a candidate passes to be called missing (``significance_rule``)."""
    return (f"significant: F test of the refit against the model without the effect on the "
            f"same residual, samples counted by their effective number (lag-1 autocorrelation), "
            f"p < {cand.P_VALUE:g}; material: the refit lowers that rms by at least "
            f"{100 * cand.MIN_DROP:g}% and the rms is above {cand.ABOVE_FLOOR:g}× the noise floor "
            f"of that residual (when the floor is measurable; a gravity- or gyro-tied residual "
            f"has its own)")


def floor_reliable(floor: float, reliable: bool, reason: str, rms: float, residual: str
                   ) -> tuple[bool, str]:
    """``(reliable, reason)`` of a noise floor once the fit's rms is known: a floor well above
    the sensor-residual rms cannot be the noise (:data:`FLOOR_OVER_RMS_MAX`)."""
    if not reliable or not np.isfinite(floor):
        return False, reason or "the noise floor could not be estimated"
    if residual == "sensor" and np.isfinite(rms) and floor > FLOOR_OVER_RMS_MAX * rms:
        return False, (f"the noise estimate ({floor:.3g}) is more than {FLOOR_OVER_RMS_MAX:g}× "
                       f"the fit's rms ({rms:.3g}): a fit keeps about the noise in its "
                       f"residual, so the estimate holds motion between samples, not only noise")
    return True, ""


def reported_floor(floor: float, reliable: bool) -> float:
    """The noise floor (sensor unit) as reported and used for materiality: ``floor`` when
    ``reliable`` (the first value of :func:`floor_reliable`), else NaN — a floor that is not
    reliable is not measured."""
    return floor if reliable else float("nan")


def decide(rms: float, residual: str, floor: float, reliable: bool, ranked,
           factor: float = FLOOR_FACTOR) -> str:
    """The verdict from the base model's ``rms`` on ``residual``, that residual's noise
    ``floor`` (the magnetometer's for the sensor residual, the tied residual's own for a tied
    one; ``reliable`` False when it cannot be measured) and the ranked candidates (best first,
    each with ``significant``, which already includes materiality)."""
    if ranked and ranked[0].significant:
        return "effect_missing"
    if reliable and np.isfinite(floor) and rms <= factor * floor:
        return "at_noise_floor"
    return "unexplained"
