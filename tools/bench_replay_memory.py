"""Peak memory of ``streamcal replay`` on a long recording against a short one, same run.

    python tools/bench_replay_memory.py [--short-min 5] [--long-h 4] [--keep DIR]

Simulates a short (default 5 min) and a long (default 4 h) 100 Hz track with
``streamcal.sim.simulate`` (magnetometer and IMU both at 100 Hz, on interleaved instants), writes
them with ``Track.write`` into a temp dir, then replays each in its own subprocess
(``python -m streamcal replay TRACK --json``), short first. After each, the peak resident set of
the children so far is read as ``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` (a maximum over
every child waited for: after the long run it is max(short, long)). Target: long / short ≤ 1.15
(memory bounded by the chunk and the calibrator's buffers, not by the recording's length).
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench_common import REPO


def _make(path: Path, seconds: float, seed: int) -> int:
    from streamcal.sim import simulate

    track = simulate(seconds, seed=seed, imu_rate_hz=100.0).track
    track.write(path)
    return len(track)


def _replay(path: Path) -> tuple[float, int, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "streamcal", "replay", str(path), "--json"],
                          capture_output=True, text=True, env=env)
    elapsed = time.perf_counter() - start
    if proc.returncode not in (0, 1):
        sys.exit(f"replay of {path} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    return elapsed, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--short-min", type=float, default=5.0)
    ap.add_argument("--long-h", type=float, default=4.0)
    ap.add_argument("--keep", metavar="DIR", help="write the tracks here and keep them")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_replay_mem_") as tmp:
        where = Path(args.keep or tmp)
        where.mkdir(parents=True, exist_ok=True)
        short, long_ = where / "short.csv", where / "long.csv"
        sizes = {}
        for path, seconds in ((short, 60 * args.short_min), (long_, 3600 * args.long_h)):
            if not path.exists():
                start = time.perf_counter()
                rows = _make(path, seconds, seed=1)
                print(f"simulated {path.name}: {seconds:.0f} s, {rows} rows, "
                      f"{path.stat().st_size / 1e6:.1f} MB in {time.perf_counter() - start:.1f} s",
                      flush=True)
            sizes[path] = path.stat().st_size
        t_short, rss_short, s_short = _replay(short)
        print(f"replay short: {t_short:.1f} s, peak RSS of children {rss_short / 1024:.1f} MiB",
              flush=True)
        t_long, rss_long, s_long = _replay(long_)
        print(f"replay long:  {t_long:.1f} s, peak RSS of children {rss_long / 1024:.1f} MiB "
              "(max over both runs)")
        for name, s in (("short", s_short), ("long", s_long)):
            print(f"  {name} summary: {s[:300]}")
        print(f"peak RSS long / short: {rss_long / rss_short:.3f} (target <= 1.15; the file is "
              f"{sizes[long_] / sizes[short]:.0f}x larger)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
