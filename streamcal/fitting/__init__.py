"""Every solver: ``streamcal.fit(data, method=…)`` and the pieces it is made of.

The free-direction fit (:mod:`.core`: normalization, ellipsoid fits, kernels, the robust LM,
reference methods, the one-pass sphere fit) and the gravity-/gyro-tied fits of the registration
effects (:mod:`.registration`, :mod:`.gyro_lag`) return a
:class:`~streamcal.calibration.Calibration` in canonical form and sensor units.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..calibration import DEFAULT_MODEL, Calibration
from ..errors import InputError
from .core import GRAVITY, METHODS, REGISTRATION_EFFECTS, fit_core, parse_model
from .lm import estimation_error, optimal_directions
from .result import FitResult

__all__ = ["fit", "fit_core", "FitResult", "METHODS", "GRAVITY", "estimation_error", "optimal_directions",
           "parse_model"]


def fit(data, *, sensor: str = "mag", model: str | Sequence[str] = DEFAULT_MODEL,
        add: str | Sequence[str] = (), kernel: str = "auto", method: str = "autocal",
        tau: float | str | None = None, covariates: Mapping[str, np.ndarray] | None = None,
        check_coverage: bool = True, stage1_max: int = 300, max_iter: int = 300,
        rtol: float = 1e-6, initial: Calibration | None = None,
        full_output: bool = False) -> Calibration | FitResult:
    """Calibrate a magnetometer (µT) or accelerometer (m/s²) from a Track or an (N,3) array.

    Registration effects (``mag_accel_misalignment``, ``time_lag``) go to the gravity- or
    gyro-tied fit; everything else to :func:`~streamcal.fitting.core.fit_core`, whose
    docstring lists the arguments. ``full_output=True`` returns a :class:`FitResult`: the
    calibration beside the solver's ``status`` (``converged``, ``stalled``, ``max_iter``),
    ``iterations`` and ``message``.
    """
    names = parse_model(model, add)
    if any(n in REGISTRATION_EFFECTS for n in names):
        # Imported here: it loads scipy.signal/stats (the gravity reference), which the
        # services that only fit K and b never need (startup on a Raspberry Pi, issue #12).
        from .registration import fit_with_registration

        if method != "autocal":
            raise InputError(f"method {method!r} fits only hard_iron, scale, soft_iron; use "
                             f"method 'autocal' for the registration effects")
        return fit_with_registration(data, names, kernel="cauchy" if kernel == "auto" else kernel,
                                     tau=None if tau in (None, "paper") else float(tau),
                                     sensor=sensor, initial=initial, full_output=full_output)
    return fit_core(data, sensor=sensor, model=names, kernel=kernel, method=method, tau=tau,
                    covariates=covariates, check_coverage=check_coverage, stage1_max=stage1_max,
                    max_iter=max_iter, rtol=rtol, initial=initial, full_output=full_output)
