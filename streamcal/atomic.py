"""Atomic file writes: temp file in the same directory, fsync, rename, fsync the directory.

A crash at any instant leaves either the old file or the new one, never a torn file (DESIGN §4.3).
A crash can leave the temp file behind; the next write of the same file removes such leftovers
once they are older than :data:`STALE_TEMP_S`, so a directory written to repeatedly does not fill
up with them.

The one rule of every output (docs/cli.md, "Output files"): missing parent directories are
created; ``-`` (:data:`STDOUT`) is standard output; a target that exists and is not a regular
file (``/dev/stdout``, a pipe, a character device) is written directly, since it cannot be
replaced; a directory, or a place that cannot be written, raises an :class:`OSError` whose
``filename`` is the target and whose ``strerror`` says what is wrong.
"""
from __future__ import annotations

import contextlib
import errno
import os
import stat
import sys
import tempfile
import time
from pathlib import Path

#: The output name that means standard output.
STDOUT = "-"
#: Directories whose symbolic links name open streams (``/dev/stdout`` → ``/proc/self/fd/1``).
_STREAM_LINK_DIRS = ("/dev/", "/proc/")

#: s, age after which a temp file is taken for the leftover of a crashed write, not a write in
#: progress in another process (a write takes milliseconds; fsync on a slow SD card, seconds).
STALE_TEMP_S = 60.0


def temp_prefix(name: str) -> str:
    """Prefix of the temp files :func:`atomic_write_bytes` creates for a target called ``name``."""
    return f".{name}."


def sweep_stale_temps(directory: str | os.PathLike, name: str | None = None,
                      older_than_s: float = STALE_TEMP_S) -> int:
    """Remove temp files of interrupted atomic writes in ``directory`` (for the target ``name``,
    or for any target), keeping those younger than ``older_than_s``; returns how many went."""
    prefix = temp_prefix(name) if name is not None else "."
    now, removed = time.time(), 0
    for entry in os.scandir(directory):
        if not (entry.name.startswith(prefix) and entry.name.endswith(".tmp")
                and entry.is_file(follow_symlinks=False)):
            continue
        try:
            if now - entry.stat(follow_symlinks=False).st_mtime > older_than_s:
                os.unlink(entry.path)
                removed += 1
        except FileNotFoundError:
            pass  # another writer's sweep got there first
    return removed


def atomic_write_bytes(path: str | os.PathLike, data: bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` atomically, by the module's rule (``-`` and streams are
    written in place; a symbolic link that is no stream is refused)."""
    with atomic_open(path, mode) as handle:
        handle.write(data)


def atomic_write_text(path: str | os.PathLike, text: str, mode: int = 0o600) -> None:
    """Text (UTF-8) version of :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"), mode)


def is_stdout(path) -> bool:
    """Whether the output ``path`` is standard output: ``-``, or a stream that is the same file
    as this process's standard output (``/dev/stdout``, ``/proc/self/fd/1``)."""
    if not isinstance(path, (str, os.PathLike)):
        return False
    if os.fspath(path) == STDOUT:
        return True
    if not is_stream(Path(path)):
        return False
    try:
        return os.path.samestat(os.stat(path), os.fstat(sys.stdout.fileno()))
    except (OSError, ValueError, AttributeError):   # no file behind sys.stdout (captured)
        return False


def output_error(path, exc: OSError | int, why: str = "") -> OSError:
    """An OSError naming the target ``path`` (not a temp file or a parent) and what is wrong."""
    code = exc if isinstance(exc, int) else (exc.errno or errno.EIO)
    text = why or (exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc))
    return OSError(code, text, os.fspath(path))


def is_stream(path: Path) -> bool:
    """``path`` exists and cannot be replaced by a rename: it is not a regular file (a FIFO, a
    character device, a socket), or it is an open stream's link (``/dev/stdout``, which points
    to whatever standard output is, a regular file included)."""
    try:
        info = os.stat(path)
    except OSError:
        return False
    if not stat.S_ISREG(info.st_mode):
        return not stat.S_ISDIR(info.st_mode)
    return path.is_symlink() and os.path.abspath(path).startswith(_STREAM_LINK_DIRS)


def output_dir(path: str | os.PathLike, mode: int = 0o777) -> Path:
    """The directory ``path``, created with its parents when missing; an :class:`OSError`
    naming ``path`` when it is something else, cannot be created or cannot be written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise output_error(path, errno.ENOTDIR, "exists and is not a directory")
    try:
        os.makedirs(path, mode=mode, exist_ok=True)
    except OSError as exc:
        raise output_error(path, exc,
                           f"cannot create the directory ({exc.strerror or exc})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise output_error(path, errno.EACCES, "directory not writable")
    return path


def prepare_output(path: str | os.PathLike) -> Path:
    """Check that the file ``path`` can be written by :func:`atomic_open` before the work that
    produces it: its missing parent directories are created; a directory, a symbolic link that
    is no stream, or a place that cannot be written raises an :class:`OSError` naming ``path``.
    Returns the directory the file goes into (``.`` for standard output and streams)."""
    if is_stdout(path) or is_stream(Path(path)):
        return Path(".")
    path = Path(path)
    if path.is_symlink():
        raise output_error(path, errno.EPERM, "refusing to replace a symbolic link")
    if path.is_dir():
        raise output_error(path, errno.EISDIR, "is a directory, not a file")
    directory = path.parent if str(path.parent) else Path(".")
    try:
        output_dir(directory)
    except OSError as exc:
        raise output_error(path, exc, f"{exc.filename}: {exc.strerror}") from None
    return directory


@contextlib.contextmanager
def _direct(handle):
    """Write to an open stream as it is (it is flushed, neither synced nor closed)."""
    yield handle
    handle.flush()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: int = 0o600):
    """A binary file handle to write ``path`` in pieces: the bytes go to a temp file in the same
    directory, which replaces ``path`` (fsync, rename, fsync the directory) when the ``with``
    block ends normally; on an exception the temp file is removed and ``path`` left as it was.
    ``-`` and streams (``/dev/stdout``, pipes) are written directly (see the module's rule)."""
    if is_stdout(path):
        sys.stdout.flush()           # text printed before keeps its place
        with _direct(sys.stdout.buffer) as handle:
            yield handle
        return
    path = Path(path)
    if is_stream(path):
        try:
            stream = open(path, "ab")   # a link to a regular file: never truncate what is there
        except OSError as exc:
            raise output_error(path, exc) from None
        with stream, _direct(stream) as handle:
            yield handle
        return
    directory = prepare_output(path)
    sweep_stale_temps(directory, path.name)
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".tmp", dir=directory)
    except OSError as exc:
        raise output_error(path, exc, f"cannot write: {exc.strerror or exc}") from None
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
