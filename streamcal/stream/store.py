"""The state directory: the calibration in use and a bounded history of accepted calibrations.

Layout::

    STATE_DIR/            0700
      calibration.json    0600, the calibration in use (docs/calibration_file.md), replaced
      atomically
      history/NNNN.json   0600, the last ``keep`` accepted calibrations, NNNN increasing

Every write goes through :func:`streamcal.atomic.atomic_write_text` (temp file, fsync, rename),
so a crash at any instant leaves a complete file. Loading validates and, if the current file is
damaged or missing, falls back to the newest good history file, saying why. Symbolic links are
refused everywhere (a link planted in a state dir must not redirect our writes or reads).
"""
from __future__ import annotations

import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

from ..atomic import atomic_write_text, output_dir, sweep_stale_temps
from ..calibration import Calibration
from ..errors import CalibrationFileError, InputError

CURRENT = "calibration.json"
HISTORY = "history"
_HISTORY_NAME = re.compile(r"^(\d{4,})\.json$")


@dataclass
class LoadResult:
    """What :meth:`CalibrationStore.load` found: the calibration (or None), the file it came
    from, and the problems met on the way (one message per rejected file)."""

    calibration: Calibration | None
    path: Path | None
    problems: list[str] = field(default_factory=list)

    @property
    def fell_back(self) -> bool:
        return self.path is not None and self.path.name != CURRENT


class CalibrationStore:
    """Atomic calibration file plus bounded history in a private state directory.

    Usage::

        store = CalibrationStore("~/.local/state/streamcal", keep=20)
        result = store.load()          # .calibration, .path, .problems
        store.save(cal)                # history/NNNN.json, then calibration.json
    """

    def __init__(self, state_dir: str | os.PathLike, keep: int = 20):
        if keep < 1:
            raise ValueError(f"keep must be ≥ 1, got {keep}")
        self.dir = Path(os.path.expanduser(os.fspath(state_dir)))
        self.keep = int(keep)
        self.history_dir = self.dir / HISTORY
        for d in (self.dir, self.history_dir):
            _private_dir(d)
        self._clean_temp_files()
        self._prune()  # saves killed before their pruning leave extra history files

    @property
    def current_path(self) -> Path:
        return self.dir / CURRENT

    def _prune(self) -> None:
        for old in self.history()[:-self.keep]:
            old.unlink(missing_ok=True)

    def history(self) -> list[Path]:
        """History files, oldest first."""
        found = []
        for entry in os.scandir(self.history_dir):
            match = _HISTORY_NAME.match(entry.name)
            if match and entry.is_file(follow_symlinks=False):
                found.append((int(match.group(1)), Path(entry.path)))
        return [p for _, p in sorted(found)]

    def save(self, cal: Calibration) -> Path:
        """Record ``cal`` in the history and make it the current calibration; returns the
        history file. Old history beyond ``keep`` files is removed."""
        text = cal.to_json() + "\n"
        files = self.history()
        number = int(_HISTORY_NAME.match(files[-1].name).group(1)) + 1 if files else 1
        entry = self.history_dir / f"{number:04d}.json"
        _write(entry, text)
        _write(self.current_path, text)
        self._prune()
        return entry

    def load(self) -> LoadResult:
        """The current calibration, or the newest good history file if the current one is
        missing or damaged; ``problems`` says why each rejected file was rejected."""
        problems = []
        for path in [self.current_path] + self.history()[::-1]:
            if not os.path.lexists(path):
                problems.append(f"{path}: missing")
                continue
            try:
                return LoadResult(Calibration.load(path), path, problems)
            except CalibrationFileError as exc:
                problems.append(str(exc))
        return LoadResult(None, None, problems)

    def _clean_temp_files(self) -> None:
        # Leftovers of writes interrupted by a crash (the renamed-over files are intact); only
        # old ones, so that a write in progress in another process is left alone.
        for d in (self.dir, self.history_dir):
            sweep_stale_temps(d)


def _private_dir(path: Path) -> None:
    if path.is_symlink():
        raise InputError(f"{path}: state directory is a symbolic link; refusing to use it")
    if not path.exists():
        output_dir(path, mode=0o700)       # its parents too; says when it cannot be made
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode):
        raise InputError(f"{path}: exists and is not a directory")
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        raise InputError(f"{path}: state directory belongs to another user (uid {info.st_uid})")
    if stat.S_IMODE(info.st_mode) & 0o077:
        os.chmod(path, 0o700)


def _write(path: Path, text: str) -> None:
    try:
        atomic_write_text(path, text, mode=0o600)
    except OSError as exc:
        raise InputError(f"{path}: cannot write calibration ({exc})") from None

