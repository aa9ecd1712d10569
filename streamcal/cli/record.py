"""``streamcal record (--bus N | --port DEV) -o TRACK.csv``: record a track
(docs/tracks_and_inputs.md).

Rows are written as sampled (``t,ax,ay,az,gx,gy,gz,mx,my,mz,temp``, empty cells where a sensor
had no new value), ``t`` in seconds from the first sample, with metadata naming the sensor and
the source. Write strategy: rows stream into a temp file beside ``TRACK.csv`` (``.TRACK.csv.*.tmp``,
flushed after every block, fsynced every few seconds) that is renamed onto ``TRACK.csv`` at the
end (``--seconds`` reached, end of a ``fake:``/``simavr:`` replay, SIGINT or SIGTERM). So memory stays small
however long the recording, ``TRACK.csv`` is never seen half-written, and after a crash the rows
so far are in the temp file. A name ending in ``.gz`` is gzip-compressed.
"""
from __future__ import annotations

import datetime as _dt
import gzip
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ._common import add_skip_bad_rows

COLUMNS = ("t", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz", "temp")
FSYNC_EVERY_S = 5.0


def register(sub) -> None:
    p = sub.add_parser("record", help="record a track from the sensor",
                       description="Record samples from the I2C sensor or the serial board into "
                                   "a track file (docs/tracks_and_inputs.md).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--bus", metavar="N|fake:TRACK.csv", help="I2C bus number or fake:TRACK.csv")
    src.add_argument("--port", metavar="DEV|fake:TRACK.csv|simavr:TRACK.csv",
                     help="serial device, pyserial URL, fake:TRACK.csv or simavr:TRACK.csv (the "
                          "compiled sketch in simavr)")
    p.add_argument("--address", default="0x68", help="MPU-9250 I2C address (default: %(default)s)")
    p.add_argument("--baud", type=int, default=115200, help="serial baud rate (default: %(default)s)")
    p.add_argument("-o", "--output", required=True, metavar="TRACK.csv",
                   help="track file to write (.csv or .csv.gz; - for stdout)")
    p.add_argument("--seconds", type=float, metavar="S", help="stop after S seconds of samples")
    add_skip_bad_rows(p)   # of a fake:/simavr: replay's track
    p.set_defaults(func=run)


class TrackWriter:
    """Stream sample blocks into a temp file beside ``path``; :meth:`commit` renames it over
    ``path``, :meth:`abort` removes it. Columns are fixed at the first block (the standard ones
    plus that block's auxiliary channels). ``-`` (stdout), ``/dev/stdout`` and pipes are written
    directly (``tmp`` is then None), by the rule of :mod:`streamcal.atomic`."""

    def __init__(self, path: str | os.PathLike, metadata: dict):
        from ..atomic import is_stdout, is_stream, output_error, prepare_output
        from ..inputs.trackio import check_metadata

        self.path = Path(path)
        self.metadata = check_metadata(metadata)
        directory = prepare_output(path)
        self.tmp = None
        if is_stdout(path):
            sys.stdout.flush()
            self._raw = sys.stdout.buffer
        elif is_stream(self.path):          # a pipe, a device
            self._raw = open(self.path, "ab")
        else:
            try:
                fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp",
                                                dir=directory)
            except OSError as exc:
                raise output_error(path, exc, f"cannot write: {exc.strerror or exc}") from None
            os.fchmod(fd, 0o644)
            self._raw = os.fdopen(fd, "wb")
        self._out = gzip.GzipFile(fileobj=self._raw, mode="wb", mtime=0) \
            if self.path.name.endswith(".gz") else self._raw
        self.columns: tuple[str, ...] | None = None
        self.rows = 0
        self.mag_rows = 0
        self.t0: float | None = None
        self._t_last = -np.inf
        self._shift = 0.0
        self.time_resets = 0
        self._synced = time.monotonic()

    def write(self, block) -> None:
        n = len(block)
        if n == 0:
            return
        if self.columns is None:
            self.columns = COLUMNS + tuple(block.aux)
            self.t0 = float(block.t[0])
            head = ["# streamcal-track: 1"] + [f"# {k}: {v}" for k, v in self.metadata.items()
                                               if k != "streamcal-track"]
            self._out.write(("\n".join(head + [",".join(self.columns)]) + "\n").encode())
        t = np.asarray(block.t, dtype=float) - self.t0 + self._shift
        if t[0] < self._t_last:            # the board rebooted (its clock restarted): continue
            self._shift += self._t_last - t[0]
            t = t + (self._t_last - t[0])
            self.time_resets += 1
        t = np.maximum.accumulate(t)
        self._t_last = float(t[-1])
        nan3, nan1 = np.full((n, 3), np.nan), np.full(n, np.nan)
        parts = [t[:, None]] + [np.asarray(a, dtype=float).reshape(n, 3) if a is not None else nan3
                                for a in (block.accel, block.gyro, block.mag)]
        parts.append((np.asarray(block.temp, dtype=float) if block.temp is not None else nan1)[:, None])
        parts += [np.asarray(block.aux.get(name, nan1), dtype=float)[:, None]
                  for name in self.columns[len(COLUMNS):]]
        table = np.hstack(parts)
        cells = [list(map(repr, col)) for col in table.T.tolist()]
        for k, col in enumerate(table.T):
            for i in np.flatnonzero(~np.isfinite(col)):
                cells[k][i] = ""
        self._out.write(("\n".join(map(",".join, zip(*cells))) + "\n").encode())
        self.rows += n
        self.mag_rows += int(np.all(np.isfinite(table[:, 7:10]), axis=1).sum())
        self._out.flush()
        if self.tmp is not None and time.monotonic() - self._synced > FSYNC_EVERY_S:
            os.fsync(self._raw.fileno())
            self._synced = time.monotonic()

    def commit(self) -> None:
        """Finish the file and rename it onto ``path`` (atomic; the directory is fsynced)."""
        if self._out is not self._raw:
            self._out.close()
        self._raw.flush()
        if self.tmp is None:               # a stream: written as it came
            if self._raw is not sys.stdout.buffer:
                self._raw.close()
            return
        os.fsync(self._raw.fileno())
        self._raw.close()
        os.replace(self.tmp, self.path)
        dir_fd = os.open(self.path.parent if str(self.path.parent) else ".", os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)

    def abort(self) -> None:
        if self.tmp is None:
            if self._raw is not sys.stdout.buffer:
                self._raw.close()
            return
        try:
            self._raw.close()
        finally:
            Path(self.tmp).unlink(missing_ok=True)


def run(args) -> int:
    from ..atomic import prepare_output
    from ..errors import InputError
    from ..service import I2CBlocks, SerialBlocks, SourceUnavailable
    from ._common import fake_track_reader
    from .daemon import _address

    if args.seconds is not None and not args.seconds > 0:
        raise InputError(f"--seconds must be positive, got {args.seconds}")
    out = Path(args.output)
    prepare_output(out)                  # a place that cannot be written is said before the work
    if args.bus is not None:
        source = I2CBlocks(args.bus, _address(args.address), read_track=fake_track_reader(args))
    else:
        source = SerialBlocks(args.port, args.baud, read_track=fake_track_reader(args))
    stop: list[str] = []
    for sig, name in ((signal.SIGTERM, "SIGTERM"), (signal.SIGINT, "SIGINT")):
        signal.signal(sig, lambda s, f, name=name: stop.append(name))
    metadata = {"sensor": "mpu9250", "source": source.description, "mag_unit": "uT",
                "recorded": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "tool": "streamcal record"}
    writer = TrackWriter(out, metadata)
    backoff = 0.5
    try:
        while not stop:
            try:
                block = source.read()
            except SourceUnavailable as exc:
                print(f"streamcal record: device not answering ({exc}); retrying", file=sys.stderr)
                source.sleep(backoff)
                backoff = min(2 * backoff, 10.0)
                continue
            backoff = 0.5
            if block is None:
                if source.finished:
                    break
                continue
            if args.seconds is not None and writer.t0 is not None:
                keep = np.asarray(block.t) - writer.t0 < args.seconds
                if not keep.all():
                    block = _head(block, int(keep.sum()))
                    stop.append("--seconds reached")
            writer.write(block)
            if args.seconds is not None and writer.t0 is not None and writer._t_last >= args.seconds:
                stop.append("--seconds reached")
    except BaseException:
        writer.abort()
        source.close()
        raise
    source.close()
    if writer.rows == 0:
        writer.abort()
        print("streamcal record: no samples arrived; nothing written", file=sys.stderr)
        return 1
    writer.commit()
    why = stop[0] if stop else "end of replay"
    print(f"streamcal record: wrote {writer.rows} rows ({writer.mag_rows} with the magnetometer) "
          f"to {out} ({why})" + (f"; board clock restarted {writer.time_resets} times"
                                 if writer.time_resets else ""), file=sys.stderr)
    return 0


def _head(block, k: int):
    import dataclasses

    cut = lambda a: None if a is None else np.asarray(a)[:k]  # noqa: E731
    return dataclasses.replace(block, t=cut(block.t), mag=cut(block.mag), accel=cut(block.accel),
                               gyro=cut(block.gyro), temp=cut(block.temp),
                               aux={k_: np.asarray(v)[:k] for k_, v in block.aux.items()})
