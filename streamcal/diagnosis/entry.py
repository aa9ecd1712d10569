"""``streamcal.diagnose``: the fresh-fit diagnosis of :mod:`.diagnosis`, or — for a calibration
the user already holds, or a recording that covers too little of the sphere for a fresh fit —
the diagnosis against held parameters of :mod:`.against` (issue #10)."""
from __future__ import annotations

from typing import Sequence

from ..calibration import DEFAULT_MODEL
from ..errors import InsufficientDataError
from ..model import REGISTRATION_EFFECTS
from . import diagnosis as _fresh
from .against import diagnose_against


def diagnose(track, model: Sequence[str] = DEFAULT_MODEL, *, calibration=None,
             calibration_source: str | None = None, **kwargs):
    """Diagnose ``track``.

    - ``calibration`` given (a :class:`~streamcal.calibration.Calibration` without registration
      effects): relative to it, re-estimating only what the recording determines
      (:func:`streamcal.diagnosis.against.diagnose_against`; ``calibration_source`` names where
      it came from in the result). A calibration with registration effects goes to the fresh
      diagnosis as before (used instead of fitting the base model).
    - otherwise :func:`streamcal.diagnosis.diagnosis.diagnose` (every keyword passed on,
      unchanged); when that refuses because the recording cannot determine a fresh fit, and
      no custom ``fitter`` was given, the recording is diagnosed against the stated default
      calibration instead (held parameters listed), which refuses in turn only when even the
      hard-iron offset cannot be determined.
    """
    if calibration is not None and not any(n in REGISTRATION_EFFECTS for n in calibration.model):
        return diagnose_against(track, calibration, candidates=kwargs.get("candidates"),
                                ladder=kwargs.get("ladder", True),
                                calibration_source=calibration_source)
    try:
        return _fresh.diagnose(track, model, calibration=calibration, **kwargs)
    except InsufficientDataError:
        if calibration is not None or kwargs.get("fitter") is not None or \
                any(n in REGISTRATION_EFFECTS for n in model):
            raise
    return diagnose_against(track, None, model=model, candidates=kwargs.get("candidates"),
                            ladder=kwargs.get("ladder", True))
