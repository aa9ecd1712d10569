"""streamcal — robust streaming calibration of MPU-9250 magnetometers and accelerometers.

    import streamcal
    track = streamcal.Track.read("log.csv")
    cal = streamcal.fit(track)          # or an (N,3) array
    x = cal.apply(m)                    # (N,3) unit directions
    dx = streamcal.diagnose(track, model=cal.model)

Public API (docs/python_api.md):

- ``Track``: a recording as columns of float64 samples (``Track.read``, ``Track.from_arrays``).
- ``fit(data, model=…, kernel=…, method=…)`` → ``Calibration``.
- ``Calibration``: the fitted model, a value (``apply``, ``save``, ``load``, ``to_dict``,
  ``from_json``); equal when the content is, whatever its ``created`` stamp.
- ``diagnose(track, model=…, calibration=None)`` → ``Diagnosis``: verdict, ranked candidates,
  ladder; a value (``to_dict``, ``Diagnosis.from_dict``).
- ``Diagnosis``: the result type of ``diagnose``.
- ``batch(paths, task, executor=None)``: ``fit`` or ``diagnose`` over many files.
- Errors: ``StreamcalError`` (base), ``InputError``, ``TrackError``, ``CalibrationFileError``,
  ``InsufficientDataError``.

``Track``, ``Calibration`` and ``Diagnosis`` show as HTML tables in Jupyter.
"""
from __future__ import annotations

from .calibration import Calibration
from .errors import (CalibrationFileError, InputError, InsufficientDataError, StreamcalError,
                     TrackError)

__version__ = "0.1.0"

__all__ = ["Calibration", "CalibrationFileError", "Diagnosis", "InputError",
           "InsufficientDataError", "StreamcalError", "Track", "TrackError", "batch", "diagnose",
           "fit"]

# The public functions are bound on first use so that ``import streamcal`` stays light for the
# command line and the daemon. No subpackage carries one of these names, so importing a
# submodule can never rebind them.
_LAZY = {"Track": ("streamcal.inputs.track", "Track"),
         "fit": ("streamcal.fitting", "fit"),
         "diagnose": ("streamcal.diagnosis", "diagnose"),
         "Diagnosis": ("streamcal.diagnosis", "Diagnosis"),
         "batch": ("streamcal.batching", "batch")}


def __getattr__(name):
    if name not in _LAZY:
        raise AttributeError(f"module 'streamcal' has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names (``__all__``): what ``dir(streamcal)`` and ``help(streamcal)`` show."""
    return sorted(__all__)
