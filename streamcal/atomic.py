"""Atomic file writes: temp file in the same directory, fsync, rename, fsync the directory.

A crash at any instant leaves either the old file or the new one, never a torn file (DESIGN §4.3).
A crash can leave the temp file behind; the next write of the same file removes such leftovers
once they are older than :data:`STALE_TEMP_S`, so a directory written to repeatedly does not fill
up with them.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
import time
from pathlib import Path

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
    """Replace ``path`` with ``data`` atomically; refuse to write through a symlink at ``path``."""
    with atomic_open(path, mode) as handle:
        handle.write(data)


def atomic_write_text(path: str | os.PathLike, text: str, mode: int = 0o600) -> None:
    """Text (UTF-8) version of :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"), mode)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: int = 0o600):
    """A binary file handle to write ``path`` in pieces: the bytes go to a temp file in the same
    directory, which replaces ``path`` (fsync, rename, fsync the directory) when the ``with``
    block ends normally; on an exception the temp file is removed and ``path`` left as it was."""
    path = Path(path)
    if path.is_symlink():
        raise OSError(f"{path}: refusing to replace a symbolic link")
    directory = path.parent if str(path.parent) else Path(".")
    sweep_stale_temps(directory, path.name)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".tmp", dir=directory)
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
