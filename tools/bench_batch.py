"""Speed-up of ``streamcal batch fit --jobs 2`` over ``--jobs 1`` on the real tracks, same run.

    python tools/bench_batch.py [--repeats 1] [--jobs 2] [--blas-threads 1]

Times ``streamcal.batch(paths, "fit", jobs=J)`` end to end (process-pool start, worker imports,
reading and fitting every track, collecting the rows) for J = 1 (the baseline) and J = --jobs,
alternating, and prints each wall time and the ratio ``t(jobs=1) / t(jobs=J)`` (median over the
repeats). The worker processes inherit ``OPENBLAS_NUM_THREADS``/``OMP_NUM_THREADS`` =
``--blas-threads`` so that one worker does not already use every core (0 leaves them as they are).
On a machine shared with other work the ratio is bounded by the cores actually free.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

from _bench_common import REAL_TRACKS


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--blas-threads", type=int, default=1)
    args = ap.parse_args()
    if args.blas_threads:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.blas_threads)
    import streamcal

    paths = sorted(str(p) for p in REAL_TRACKS.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    print(f"{len(paths)} real tracks from {REAL_TRACKS}; {os.cpu_count()} CPUs; "
          f"BLAS threads per worker: {args.blas_threads or 'default'}")
    times = {1: [], args.jobs: []}
    reference = None
    for r in range(args.repeats):
        for jobs in (1, args.jobs):
            start = time.perf_counter()
            rows = streamcal.batch(paths, "fit", jobs=jobs)
            elapsed = time.perf_counter() - start
            times[jobs].append(elapsed)
            ok = sum(row["status"] == "ok" for row in rows)
            print(f"repeat {r + 1}  --jobs {jobs}: {elapsed:7.2f} s  ({ok} of {len(rows)} ok, "
                  f"sum of per-file times {sum(row['seconds'] for row in rows):.2f} s)")
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
          f"{bound:.2f}x with {args.jobs} workers; load average {os.getloadavg()[0]:.2f} on "
          f"{os.cpu_count()} CPUs (other work on the machine takes its share)")
    print(f"speed-up --jobs {args.jobs} over --jobs 1: {t1 / tj:.2f}x "
          f"(median {t1:.2f} s vs {tj:.2f} s over {args.repeats} repeat(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
