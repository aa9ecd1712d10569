"""streamcal — robust streaming calibration of MPU-9250 magnetometers and accelerometers.

    import streamcal
    track = streamcal.Track.read("log.csv")
    cal = streamcal.fit(track)          # or an (N,3) array
    x = cal.apply(m)                    # (N,3) unit directions
    dx = streamcal.diagnose(track, model=cal.model)
"""
from __future__ import annotations

from .calibration import Calibration
from .errors import (CalibrationFileError, InputError, InsufficientDataError, StreamcalError,
                     TrackError)

__version__ = "0.1.0"

__all__ = ["Calibration", "CalibrationFileError", "InputError", "InsufficientDataError",
           "StreamcalError", "Track", "TrackError", "diagnose", "fit"]


def __getattr__(name):  # lazy: keep `import streamcal` light for the CLI and the daemon
    if name == "Track":
        from .track import Track
        return Track
    if name == "fit":
        from .fit import fit
        return fit
    if name == "diagnose":
        from .diagnose import diagnose
        return diagnose
    raise AttributeError(f"module 'streamcal' has no attribute {name!r}")
