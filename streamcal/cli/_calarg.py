"""``--cal CAL`` / ``--initial CAL``: a calibration JSON file (docs/calibration_file.md) or a daemon/replay state
directory (its ``calibration.json``, else the newest good ``history/NNNN.json``, as
:class:`streamcal.stream.store.CalibrationStore` keeps them). Read only: the directory is not
created, pruned or re-permissioned.

``--cal autopilot`` (or ``--cal log``): the calibration the autopilot had in force, rebuilt from
the recording's own parameters (ArduPilot COMPASS_*, PX4 CAL_MAGn_*:
:func:`streamcal.inputs.autopilot_calibration`)
— unless a file or directory of that name exists, which is then read as above."""
from __future__ import annotations

import os
from pathlib import Path

from ..calibration import Calibration
from ..errors import CalibrationFileError, InputError
from ..stream.store import CURRENT, HISTORY, _HISTORY_NAME


def load_calibration_arg(path: str, option: str = "--cal") -> tuple[Calibration, str]:
    """``(calibration, source)``; CalibrationFileError (exit 2) naming the file and why."""
    p = Path(os.path.expanduser(path))
    if not p.is_dir():
        if not p.exists():
            raise CalibrationFileError(f"{option} {path}: no such file or state directory")
        return Calibration.load(p), str(p)
    hist = p / HISTORY
    files = [p / CURRENT] + (sorted((f for f in hist.iterdir() if _HISTORY_NAME.match(f.name)),
                                    key=lambda f: int(_HISTORY_NAME.match(f.name).group(1)),
                                    reverse=True) if hist.is_dir() else [])
    problems = []
    for f in files:
        if not f.exists():
            problems.append(f"{f}: missing")
            continue
        try:
            return Calibration.load(f), str(f)
        except CalibrationFileError as exc:
            problems.append(str(exc))
    raise CalibrationFileError(f"{option} {path}: state directory holds no usable calibration ("
                               + "; ".join(problems) + ")")


#: ``--cal`` values that mean "the calibration in the recording's own parameters".
FROM_RECORDING = ("autopilot", "log")


def calibration_for(path: str, track, option: str = "--cal") -> tuple[Calibration, str]:
    """:func:`load_calibration_arg`, or for ``autopilot``/``log`` (no file of that name) the
    autopilot's calibration from ``track``'s parameters; CalibrationFileError (exit 2) saying
    the log carries none."""
    if path in FROM_RECORDING and not Path(path).exists():
        from ..inputs import autopilot_calibration

        try:
            cal = autopilot_calibration(track)
        except InputError as exc:
            raise CalibrationFileError(
                f"{option} {path}: the recording carries no autopilot compass calibration "
                f"({exc}); give a calibration file or state directory instead") from None
        where = dict(cal.extra or {}).get("source") or "the recording's parameters"
        return cal, f"autopilot calibration in force ({where})"
    return load_calibration_arg(path, option)


def follow_fitted_compass(args, attr: str = "cal", option: str = "--cal") -> None:
    """Without ``--compass``, set ``args.compass`` to the compass the calibration file
    ``args.<attr>`` was fitted for (its ``compass_instance``) when ``args.track`` is an autopilot
    log, and say so on stderr: one compass's calibration on another's readings would make
    every figure wrong. Nothing for ``autopilot``/``log``, a calibration of no particular
    compass, or another recording."""
    import sys

    path = getattr(args, attr, None)
    if not path or getattr(args, "compass", None) is not None or \
            (path in FROM_RECORDING and not Path(path).exists()):
        return
    fitted = (load_calibration_arg(path, option)[0].extra or {}).get("compass_instance")
    if fitted is None:
        return
    from ..inputs import detect

    if detect(Path(args.track)) not in ("dataflash", "ulog"):
        return
    args.compass = int(fitted)
    print(f"streamcal: reading compass {int(fitted)} of {args.track}, the one {path} was fitted "
          f"for (--compass N reads another)", file=sys.stderr)
