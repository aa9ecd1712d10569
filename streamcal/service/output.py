"""Calibrated samples for other programs: JSON lines on a stream or on a local UNIX socket.

One line per magnetometer sample, UTF-8, ``\\n``-terminated::

    {"t": 12.34, "field_uT": [21.3, -14.9, -38.1], "direction": [0.44, -0.31, -0.79], "cal_version": 3, "disturbed": false}

- ``t``: sample time, s, on the source's clock (driver clock: monotonic seconds on a Pi, track time
  with a fake bus; board clock for serial).
- ``field_uT``: calibrated field ``|B| K⁻¹(m − b − effect terms)`` in µT, body (accelerometer) axes;
  its norm shows what the model leaves over.
- ``direction``: the same vector normalised to unit length.
- ``cal_version``: which estimate produced the line: 0 = the running sphere estimate before any
  calibration; 1, 2, … increase each time the calibration in use changes (loaded at start,
  accepted, recalled after an environment change, re-read on SIGHUP).
- ``disturbed``: true when the sample disagrees with the calibration that produced the line by the
  calibrator's own criterion, the one that holds samples back from fitting (relative error
  ``|‖x‖ − 1|`` beyond the drift limit on the directions the calibration was fitted on, or beyond
  half the field anywhere: a phone or a magnet passing, or an environment change not yet
  recalibrated). Its ``field_uT`` and ``direction`` are then not the Earth field alone: a heading
  filter should not trust them. Always false with ``cal_version`` 0 (no calibration yet).
  :meth:`streamcal.stream.StreamingCalibrator.disagreement` computes it.

Samples before any estimate exists are not written. The socket is ``SOCK_STREAM``: connect
(``socat - UNIX-CONNECT:/run/streamcal/samples.sock``) and read lines; each client gets lines from
the moment it connects. A client that does not keep up loses whole lines (never parts of one), at
most ``max_pending`` bytes wait per client, so memory stays bounded; nothing a client sends is read.
"""
from __future__ import annotations

import errno
import os
import socket
import stat
from pathlib import Path
from typing import TextIO

import numpy as np

#: Bytes queued per socket client before new lines are dropped for it.
MAX_PENDING = 256 * 1024
MAX_CLIENTS = 16


def format_lines(t, field, cal_version: int, disturbed=None) -> str:
    """JSON lines (module docstring) for rows of ``field`` (n,3) µT at times ``t`` (n,);
    ``disturbed`` (n,) bool (None: all false). Rows with a non-finite or zero field are
    skipped. Returns ``""`` when none is left."""
    t = np.asarray(t, dtype=float)
    field = np.asarray(field, dtype=float).reshape(-1, 3)
    norm = np.linalg.norm(field, axis=1)
    ok = np.isfinite(norm) & (norm > 0) & np.isfinite(t)
    if not ok.any():
        return ""
    rows = np.column_stack([t[ok], field[ok], field[ok] / norm[ok, None]])
    head = ('{{"t": {:.6f}, "field_uT": [{:.4f}, {:.4f}, {:.4f}], '
            '"direction": [{:.6f}, {:.6f}, {:.6f}], "cal_version": %d, ' % int(cal_version))
    calm = head + '"disturbed": false}}\n'
    if disturbed is None:
        return "".join(calm.format(*row) for row in rows.tolist())
    flags = np.asarray(disturbed, dtype=bool).reshape(-1)
    if flags.shape != t.shape:
        raise ValueError(f"format_lines: disturbed has {flags.size} rows, t has {t.size}")
    flags = flags[ok]
    if not flags.any():
        return "".join(calm.format(*row) for row in rows.tolist())
    templates = (calm, head + '"disturbed": true}}\n')
    return "".join(templates[f].format(*row) for row, f in zip(rows.tolist(), flags.tolist()))


class SocketOutput:
    """A listening ``SOCK_STREAM`` UNIX socket at ``path`` that copies lines to every client.

    Non-blocking throughout: :meth:`publish` accepts new clients, writes what each socket takes,
    queues the rest up to ``max_pending`` bytes and counts lines dropped beyond that.
    An existing socket file at ``path`` (a previous run) is replaced; any other file is refused.
    """

    def __init__(self, path: str | os.PathLike, mode: int = 0o660,
                 max_pending: int = MAX_PENDING, max_clients: int = MAX_CLIENTS):
        self.path = Path(path)
        self.max_pending, self.max_clients = int(max_pending), int(max_clients)
        self.dropped_lines = 0
        self.clients_served = 0
        self._clients: dict[socket.socket, bytearray] = {}
        try:
            info = os.lstat(self.path)
        except FileNotFoundError:
            info = None
        if info is not None:
            if not stat.S_ISSOCK(info.st_mode):
                from ..errors import InputError
                raise InputError(f"--socket {self.path}: exists and is not a socket; refusing to "
                                 "replace it")
            self.path.unlink()
        self._server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        try:
            self._server.bind(os.fspath(self.path))
            os.chmod(self.path, mode)
            self._server.listen(self.max_clients)
        except OSError as exc:
            self._server.close()
            from ..errors import InputError
            raise InputError(f"--socket {self.path}: cannot listen ({exc.strerror or exc})") from None
        self._server.setblocking(False)

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._server.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if len(self._clients) >= self.max_clients:
                conn.close()
                continue
            conn.setblocking(False)
            conn.shutdown(socket.SHUT_RD)
            self._clients[conn] = bytearray()
            self.clients_served += 1

    def publish(self, text: str) -> None:
        """Queue ``text`` (whole lines) for every client and write what the sockets take."""
        self._accept()
        data = text.encode("utf-8") if text else b""
        n_lines = text.count("\n")
        for conn, pending in list(self._clients.items()):
            if data:
                room = self.max_pending - len(pending)
                if len(data) <= room:
                    pending += data
                else:                       # queue the whole lines that fit, drop the rest
                    cut = data.rfind(b"\n", 0, max(room, 0)) + 1
                    pending += data[:cut]
                    self.dropped_lines += n_lines - data.count(b"\n", 0, cut)
            if pending:
                try:
                    sent = conn.send(pending, socket.MSG_NOSIGNAL)
                    del pending[:sent]
                except (BlockingIOError, InterruptedError):
                    pass
                except OSError as exc:      # EPIPE, ECONNRESET: the client left
                    if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK):
                        self._drop(conn)

    def _drop(self, conn) -> None:
        self._clients.pop(conn, None)
        conn.close()

    def close(self) -> None:
        for conn in list(self._clients):
            self._drop(conn)
        self._server.close()
        try:
            if stat.S_ISSOCK(os.lstat(self.path).st_mode):
                self.path.unlink()
        except FileNotFoundError:
            pass


class StreamOutput:
    """JSON lines on a text stream (stdout); a closed pipe turns the output off, not the service."""

    def __init__(self, stream: TextIO):
        self.stream = stream
        self.broken = False

    def publish(self, text: str) -> None:
        if not text or self.broken:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (BrokenPipeError, ValueError, OSError):
            self.broken = True

    def close(self) -> None:
        pass


class Outputs:
    """The configured outputs together; ``cal_version`` as described in the module docstring."""

    def __init__(self, sinks=()):
        self.sinks = list(sinks)
        self.lines = 0

    def __bool__(self) -> bool:
        return bool(self.sinks)

    def publish(self, t, field, cal_version: int, disturbed=None) -> None:
        """Format (:func:`format_lines`) and send to every sink; ``disturbed`` (n,) bool or None."""
        if not self.sinks:
            return
        text = format_lines(t, field, cal_version, disturbed)
        self.lines += text.count("\n")
        for sink in self.sinks:
            sink.publish(text)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()
