"""``streamcal.diagnose``: the fresh-fit diagnosis of :mod:`.diagnosis`, or — for a calibration
the user already holds, or a recording that covers too little of the sphere for a fresh fit —
the diagnosis against held parameters of :mod:`.against` (issue #10)."""
from __future__ import annotations

from typing import Sequence

from ..calibration import DEFAULT_MODEL
from ..constants import ATTITUDE_COLUMNS
from ..errors import InsufficientDataError
from ..model import REGISTRATION_EFFECTS
from . import advice
from . import diagnosis as _fresh
from .against import diagnose_against


def diagnose(track, model: Sequence[str] = DEFAULT_MODEL, *, calibration=None,
             calibration_source: str | None = None, recording: Sequence[str] | None = None,
             cal_arg: str | None = None, location: dict | None = None, **kwargs):
    """Diagnose ``track``.

    - ``calibration`` given (a :class:`~streamcal.calibration.Calibration` without registration
      effects): relative to it, re-estimating only what the recording determines
      (:func:`streamcal.diagnosis.against.diagnose_against`; ``calibration_source`` names where
      it came from in the result). A calibration with registration effects goes to the fresh
      diagnosis as before (used instead of fitting the base model).
    Then the plain words of :mod:`streamcal.diagnosis.advice`: ``next_step`` names the
    recording as ``recording`` (argv words; default its path) and a held calibration as
    ``cal_arg``; ``location`` (:func:`streamcal.geomag.wmm_field`; default the log's GPS
    position and date when it has them) gives the horizontal field for ``heading_error_deg``;
    the result carries the place it used as ``location``.

    - otherwise :func:`streamcal.diagnosis.diagnosis.diagnose` (every keyword passed on,
      unchanged); when that refuses because the recording cannot determine a fresh fit, and
      no custom ``fitter`` was given, the recording is diagnosed against the stated default
      calibration instead (held parameters listed), which refuses in turn only when even the
      hard-iron offset cannot be determined.
    """
    d = _engine(track, model, calibration, calibration_source, location, kwargs)
    if recording is None:
        recording = [str(track.path) if getattr(track, "path", None) else "TRACK"]
    # the held fit used the attitude reference at a place the user gave: the pasted command
    # needs it too, for the promise to be what it gives
    place = advice.place_argv(location) if location is not None and d.held is not None \
        and d.held.attitude_reference else []
    if location is None:   # the log's own GPS position and date, when it has them
        from ..errors import InputError
        from ..fitting.attitude_reference import log_location

        try:
            location = log_location(track)[0]
        except InputError:
            location = None
    if calibration is not None and d.held is not None and d.last_calibration is not None \
            and all(track.has(c) for c in ATTITUDE_COLUMNS):
        from ..fitting.heading_check import heading_check

        d = d.replace(heading_check=heading_check(track, calibration, d.last_calibration,
                                                  location))
    gravity = d.gravity if d.gravity is not None else kwargs.get("gravity")
    h, why = advice.horizontal_field(track, d.calibration, location, gravity)
    heading = advice.heading_error(d, h)
    d = d.replace(heading_error_deg=heading, heading_error_reason="" if heading else why,
                  location=location)
    d = d.replace(next_step=advice.next_step(d, list(recording), cal_arg, place=place))
    return d.replace(summary=advice.summary(d))


def _engine(track, model, calibration, calibration_source, location, kwargs):
    if calibration is not None and not any(n in REGISTRATION_EFFECTS for n in calibration.model):
        return diagnose_against(track, calibration, candidates=kwargs.get("candidates"),
                                ladder=kwargs.get("ladder", True),
                                calibration_source=calibration_source, location=location)
    try:
        return _fresh.diagnose(track, model, calibration=calibration, **kwargs)
    except InsufficientDataError:
        if calibration is not None or kwargs.get("fitter") is not None or \
                any(n in REGISTRATION_EFFECTS for n in model):
            raise
    return diagnose_against(track, None, model=model, candidates=kwargs.get("candidates"),
                            ladder=kwargs.get("ladder", True), location=location)
