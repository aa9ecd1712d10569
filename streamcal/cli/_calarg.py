"""``--cal CAL`` / ``--initial CAL``: a calibration JSON file (docs/calibration_file.md) or a
daemon/replay state directory (its ``calibration.json``, else the newest good
``history/NNNN.json``, as :class:`streamcal.stream.store.CalibrationStore` keeps them). Read
only: the directory is not created, pruned or re-permissioned."""
from __future__ import annotations

import os
from pathlib import Path

from ..calibration import Calibration
from ..errors import CalibrationFileError
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
