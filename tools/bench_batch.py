"""Speed-up of ``streamcal batch fit --jobs 2`` over ``--jobs 1`` on the real tracks, same run.

    python tools/bench_batch.py [--repeats 1] [--jobs 2] [--blas-threads 1] [--files N] [--quick]

Times ``streamcal.batch(paths, "fit", jobs=J)`` end to end (process-pool start, worker imports,
reading and fitting every track, collecting the rows) for J = 1 (the baseline) and J = --jobs,
alternating, and prints each wall time and the ratio ``t(jobs=1) / t(jobs=J)`` (median over the
repeats). The worker processes inherit ``OPENBLAS_NUM_THREADS``/``OMP_NUM_THREADS`` =
``--blas-threads`` so that one worker does not already use every core (0 leaves them as they are).

On a machine shared with other work the ratio is bounded by the cores actually free, so each run
also prints what tells whether they were: the load average (1 min) at its start and end, the
CPU time of each file's fit next to its wall time (``wall / CPU`` near 1: the worker had a core
to itself; near 2: it ran on a core shared with one other busy process), and the workers' total
CPU time over the run's wall time (the cores the run actually got: up to J). A speed-up below J
with ``wall / CPU`` well above 1 under ``--jobs J`` says the cores were busy, not that the batch
does not scale.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

from _bench_common import REAL_TRACKS

#: Where :func:`_timed_fit` appends "path<TAB>CPU seconds" lines (set before the workers start).
_CPU_LOG = "STREAMCAL_BENCH_BATCH_CPU_LOG"


def _timed_fit(path: str) -> dict:
    """``fit_task`` with the worker's CPU time for this file appended to the file named by
    ``$STREAMCAL_BENCH_BATCH_CPU_LOG`` (a summary row only carries the wall time)."""
    from streamcal.batching import fit_task

    start = time.process_time()
    try:
        return fit_task(path)
    finally:
        with open(os.environ[_CPU_LOG], "a") as log:   # one short append: atomic on POSIX
            log.write(f"{path}\t{time.process_time() - start!r}\n")


def _run(paths: list[str], jobs: int, log: str) -> dict:
    """One ``batch`` run: its rows, wall time, per-file CPU, workers' CPU and load average."""
    import resource

    import streamcal

    open(log, "w").close()
    os.environ[_CPU_LOG] = log
    load0 = os.getloadavg()[0]
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    rows = streamcal.batch(paths, _timed_fit, jobs=jobs)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)   # the pool's workers, joined by batch
    cpu = {}
    with open(log) as handle:
        for line in handle:
            path, seconds = line.rstrip("\n").rsplit("\t", 1)
            cpu[path] = float(seconds)
    return {"rows": rows, "wall": wall, "cpu": cpu, "load": (load0, os.getloadavg()[0]),
            "workers_cpu": (after.ru_utime + after.ru_stime)
            - (children.ru_utime + children.ru_stime)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--blas-threads", type=int, default=1)
    ap.add_argument("--files", type=int, default=0, help="only the first N tracks (0: all)")
    ap.add_argument("--quick", action="store_true", help="the first 6 tracks, one repeat")
    args = ap.parse_args()
    if args.quick:
        args.files, args.repeats = args.files or 6, 1
    if args.blas_threads:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.blas_threads)

    paths = sorted(str(p) for p in REAL_TRACKS.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    paths = paths[:args.files] if args.files else paths
    print(f"{len(paths)} real tracks from {REAL_TRACKS}; {os.cpu_count()} CPUs; "
          f"BLAS threads per worker: {args.blas_threads or 'default'}; load average (1/5/15 "
          f"min) at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    times = {1: [], args.jobs: []}
    per_file = {1: [], args.jobs: []}            # wall / CPU of every file, all repeats
    reference = None
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        for r in range(args.repeats):
            for jobs in (1, args.jobs):
                run = _run(paths, jobs, os.path.join(tmp, "cpu.log"))
                rows, wall = run["rows"], run["wall"]
                times[jobs].append(wall)
                ok = sum(row["status"] == "ok" for row in rows)
                file_wall = sum(row["seconds"] for row in rows)
                file_cpu = sum(run["cpu"].get(row["path"], float("nan")) for row in rows)
                per_file[jobs] += [row["seconds"] / run["cpu"][row["path"]] for row in rows
                                   if run["cpu"].get(row["path"])]
                print(f"repeat {r + 1}  --jobs {jobs}: {wall:7.2f} s wall  ({ok} of {len(rows)} "
                      f"ok); per file: wall {file_wall:.2f} s, CPU {file_cpu:.2f} s in all "
                      f"(wall / CPU {file_wall / file_cpu:.2f}); workers' CPU "
                      f"{run['workers_cpu']:.2f} s = {run['workers_cpu'] / wall:.2f} cores "
                      f"busy of {jobs}; load average {run['load'][0]:.2f} -> "
                      f"{run['load'][1]:.2f}", flush=True)
                strip = [{k: v for k, v in row.items() if k != "seconds"} for row in rows]
                if reference is None:
                    reference, reference_seconds = strip, [row["seconds"] for row in rows]
                elif strip != reference:
                    print("ERROR: the rows differ between runs", file=sys.stderr)
                    return 1
    t1, tj = statistics.median(times[1]), statistics.median(times[args.jobs])
    longest = max(reference_seconds)
    bound = min(args.jobs, sum(reference_seconds) / longest)
    print(f"longest file {longest:.2f} s of {sum(reference_seconds):.2f} s (jobs=1): at most "
          f"{bound:.2f}x with {args.jobs} workers")
    for jobs, ratios in per_file.items():
        print(f"  --jobs {jobs}: per-file wall / CPU median {statistics.median(ratios):.2f} "
              f"(range {min(ratios):.2f}-{max(ratios):.2f} over {len(ratios)} files; 1.00: a "
              "core to itself)")
    print(f"load average (1/5/15 min) at end {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs (other work on the machine takes its share)")
    print(f"speed-up --jobs {args.jobs} over --jobs 1: {t1 / tj:.2f}x "
          f"(median {t1:.2f} s vs {tj:.2f} s over {args.repeats} repeat(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
