"""The error hierarchy of streamcal.

Every error a user can cause names *where* (file/line/column, register, frame) and *what*.
The CLI maps them to exit codes: :class:`InputError` → 2, :class:`InsufficientDataError` → 1.
"""
from __future__ import annotations


class StreamcalError(Exception):
    """Base class of every error streamcal raises on purpose."""

    exit_code = 2


class InputError(StreamcalError):
    """Bad user input: a file, an option or a value that cannot be used as given (exit code 2)."""

    exit_code = 2


class TrackError(InputError):
    """A track file that violates the track format (docs/tracks_and_inputs.md), located by file,
    line (1-based) and column name; arrays (no file) by ``row`` (0-based), which a file reader
    turns into its line."""

    def __init__(self, message: str, path: str | None = None, line: int | None = None,
                 column: str | None = None, row: int | None = None):
        self.path, self.line, self.column, self.reason, self.row = path, line, column, message, row
        where = ":".join(str(p) for p in (path, line) if p is not None)
        if column is not None:
            where += f" column '{column}'" if where else f"column '{column}'"
        super().__init__(f"{where}: {message}" if where else message)


class CalibrationFileError(InputError):
    """A calibration JSON file that is damaged, foreign or fails validation
    (docs/calibration_file.md)."""


class UnknownEffectError(InputError):
    """An effect name that is not in the catalog (docs/effects.md)."""


class MissingColumnsError(InputError):
    """An effect or sensor needs track columns that the track does not have."""


class InsufficientDataError(StreamcalError):
    """The data cannot support the request (exit code 1): too few samples, too little coverage,
    directions that leave parts of the model undetermined. The message says what is missing."""

    exit_code = 1
