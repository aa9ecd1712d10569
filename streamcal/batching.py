"""Many recordings at once: one summary row per file (docs/cli.md ``streamcal batch``).

``batch(paths, task, executor=None)`` runs a task over every file on any
:class:`concurrent.futures.Executor` — a process pool by default, ``distributed.Client(...)
.get_executor()`` to go past one machine — and returns the rows in input order. A file that
fails gives a row with ``status="error"`` and its error (exception type and message), never the
end of the run.

Tasks are top-level functions ``(path) -> dict`` so that every executor can serialize them by
reference; :data:`TASKS` names the built-in ones.
"""
from __future__ import annotations

import concurrent.futures as cf
import csv
import functools
import io
import os
import time
from typing import Callable, Iterable

#: Columns of a summary row, in CSV order. ``rms`` is on the residual named in ``residual``
#: (``sensor``: paper eq. 41 over inliers; the diagnosis may name a tied residual), sensor unit.
COLUMNS = ("path", "status", "n", "rms", "residual", "unit", "field", "coverage", "verdict",
           "top_candidate", "rms_after", "n_compared", "seconds", "error", "skipped_rows",
           "first_skipped")


def _read(path: str, skip_bad_rows: bool, compass: int | None = None):
    """The recording at ``path`` (any format the other commands read: track, autopilot log,
    capture; compass ``compass`` of a log) and its summary cells on skipped rows
    (``skipped_rows``, the first reason), filled only with ``skip_bad_rows``, and on what a cut
    or damaged log lost (``first_skipped``)."""
    from .inputs import read_recording

    track = read_recording(path, skip_bad_rows=skip_bad_rows, compass=compass)
    cells = {}
    if skip_bad_rows:
        cells = {"skipped_rows": getattr(track, "skipped_rows", 0),
                 "first_skipped": track.skip_reasons[0] if getattr(track, "skip_reasons", ())
                 else None}
    if track.metadata.get("read_warnings"):
        cells["first_skipped"] = cells.get("first_skipped") or track.metadata["read_warnings"]
    return track, cells


def fit_task(path: str, skip_bad_rows: bool = False, compass: int | None = None) -> dict:
    """Fit the default model to the recording at ``path`` (``streamcal fit`` defaults)."""
    from .fitting import fit

    track, cells = _read(path, skip_bad_rows, compass)
    cal = fit(track)
    return {"n": cal.n, "rms": cal.rms, "residual": "sensor", "unit": cal.unit,
            "field": cal.field, "coverage": cal.coverage, **cells}


def diagnose_task(path: str, skip_bad_rows: bool = False, compass: int | None = None) -> dict:
    """Diagnose the recording at ``path`` with the default model (``streamcal diagnose``
    defaults)."""
    from .diagnosis import diagnose

    track, cells = _read(path, skip_bad_rows, compass)
    d = diagnose(track)
    cal = d.calibration
    return {**cells, "n": d.n, "rms": d.rms, "residual": d.residual,
            "unit": getattr(cal, "unit", None), "field": getattr(cal, "field", None),
            "coverage": getattr(cal, "coverage", None), "verdict": d.verdict,
            "top_candidate": d.candidates[0].effect if d.candidates else None,
            # the ladder's last step: what `streamcal fit … --add …` gives, over n_compared samples
            # (``rms`` is the ladder's first step over the same samples)
            "rms_after": d.ladder[-1]["rms"] if len(d.ladder) > 1 else None,
            "n_compared": d.ladder[0].get("n") if d.ladder else None}


TASKS: dict[str, Callable[[str], dict]] = {"fit": fit_task, "diagnose": diagnose_task}


def run_one(task: Callable[[str], dict], path: str) -> dict:
    """One summary row: ``task(path)`` timed, or the error it raised (type and message)."""
    start = time.perf_counter()
    row = {"path": str(path)}
    try:
        row.update(task(str(path)))
        row["status"] = "ok"
    except Exception as exc:  # a bad file is a row, not the end of the run
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    row["seconds"] = time.perf_counter() - start
    return {key: row.get(key) for key in COLUMNS}


def _resolve(task, skip_bad_rows: bool = False,
             compass: int | None = None) -> Callable[[str], dict]:
    if callable(task):
        return task
    try:
        func = TASKS[task]
        kwargs = {"skip_bad_rows": True} if skip_bad_rows else {}
        if compass is not None:
            kwargs["compass"] = compass
        return functools.partial(func, **kwargs) if kwargs else func
    except KeyError:
        from .errors import InputError

        raise InputError(f"unknown batch task {task!r}; expected one of {', '.join(TASKS)}") from None


def batch(paths: Iterable[str | os.PathLike], task="fit", executor: cf.Executor | None = None,
          jobs: int | None = None, progress: Callable[[dict], None] | None = None,
          skip_bad_rows: bool = False, compass: int | None = None) -> list[dict]:
    """Run ``task`` (``"fit"``, ``"diagnose"`` or a picklable top-level ``(path) -> dict``) over
    every file; one row per file in input order (keys :data:`COLUMNS`).

    ``executor``: any :class:`concurrent.futures.Executor` (left open; the caller owns it). By
    default a :class:`~concurrent.futures.ProcessPoolExecutor` with ``jobs`` workers (default
    ``os.cpu_count()``), closed on return. ``progress(row)`` is called as each file finishes, in
    completion order. ``skip_bad_rows`` (named tasks): malformed rows are skipped and counted in
    the ``skipped_rows`` and ``first_skipped`` cells instead of failing the file. ``compass``
    (named tasks): the compass instance of each autopilot log (default: its first).
    """
    func = _resolve(task, skip_bad_rows, compass)
    paths = [os.fspath(p) for p in paths]
    own = executor is None
    if own:
        executor = cf.ProcessPoolExecutor(max_workers=max(1, jobs or os.cpu_count() or 1))
    rows: list[dict | None] = [None] * len(paths)
    try:
        futures = {executor.submit(run_one, func, path): k for k, path in enumerate(paths)}
        for future in cf.as_completed(futures):
            k = futures[future]
            try:
                rows[k] = future.result()
            except Exception as exc:  # the worker itself died (killed, unpicklable result, …)
                rows[k] = {key: None for key in COLUMNS} | {
                    "path": paths[k], "status": "error", "error": f"{type(exc).__name__}: {exc}"}
            if progress is not None:
                progress(rows[k])
    finally:
        if own:
            executor.shutdown(wait=True, cancel_futures=True)
    return rows


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}" if value == value else "nan"
    return str(value)


def summary_csv(rows: Iterable[dict]) -> str:
    """The rows as CSV text with a header of :data:`COLUMNS` (empty cell: not applicable)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        writer.writerow([_cell(row.get(key)) for key in COLUMNS])
    return out.getvalue()


def write_summary(path: str | os.PathLike, rows: Iterable[dict]) -> None:
    """Write the summary CSV atomically (:mod:`streamcal.atomic`)."""
    from .atomic import atomic_write_bytes

    atomic_write_bytes(path, summary_csv(rows).encode(), mode=0o644)
