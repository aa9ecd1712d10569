"""A calibration in the form its destination loads (docs/cli.md ``streamcal export``).

    text, notes = export(cal, "ardupilot")   # also "px4", "c-header", "json"

``notes`` says what the destination cannot express; each exporter also writes them into the
file as comments. One module per destination; the shared polar-decomposition step is in
:mod:`.common`.
"""
from __future__ import annotations

from ..calibration import Calibration
from ..errors import InputError
from . import ardupilot, c_header, px4

FORMATS = ("ardupilot", "px4", "c-header", "json")


def _json(cal: Calibration) -> tuple[str, list[str]]:
    return cal.to_json() + "\n", []


_EXPORTERS = {"ardupilot": ardupilot.export, "px4": px4.export, "c-header": c_header.export,
              "json": _json}


def export(cal: Calibration, fmt: str,
           firmware_version: str | None = None) -> tuple[str, list[str]]:
    """(file text, notes on what ``fmt`` cannot express) for a calibration; ``firmware_version``
    (ArduPilot only, e.g. "Copter 3.5") chooses the order COMPASS_MOT is written for."""
    try:
        exporter = _EXPORTERS[fmt]
    except KeyError:
        raise InputError(f"export: unknown format {fmt!r}; known: {', '.join(FORMATS)}") from None
    if firmware_version is not None:
        if fmt != "ardupilot":
            raise InputError(f"--firmware-version applies to --format ardupilot, not {fmt}")
        return ardupilot.export(cal, firmware_version)
    return exporter(cal)
