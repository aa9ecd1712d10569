"""Peak memory of ``streamcal replay``, ``convert`` and ``apply`` on a long recording against a
short one, same run.

    python tools/bench_replay_memory.py [--short-min 5] [--long-h 4] [--keep DIR]
        [--only replay|convert-apply]

Simulates a short (default 5 min) and a long (default 4 h) 100 Hz track with
``streamcal.sim.simulate`` (magnetometer and IMU both at 100 Hz, on interleaved instants), writes
them with ``Track.write`` into a temp dir (the long one as one-hour segments of one sensor model
end to end), then replays each in its own subprocess (``python -m streamcal replay TRACK
--json``) started by a fresh small process that reads ``resource.getrusage(RUSAGE_CHILDREN)
.ru_maxrss`` after it: the replay's own peak resident set (read in this big process, a forked
child's peak would include ours). The same for ``streamcal convert TRACK -o OUT.csv.gz`` and
``streamcal apply CAL.json TRACK -o OUT.csv`` (a fixed calibration). Target: long / short ≤ 1.15
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
    """Simulate in segments of at most an hour (one sensor model: ``K``, ``b`` of the first)
    placed end to end, and write the whole track with ``Track.write``."""
    import numpy as np

    from streamcal.inputs.track import Track
    from streamcal.sim import simulate

    first = simulate(min(seconds, 3600.0), seed=seed, imu_rate_hz=100.0)
    parts, done = [first.track.columns], min(seconds, 3600.0)
    while done < seconds:
        seg = simulate(min(seconds - done, 3600.0), seed=seed + len(parts), imu_rate_hz=100.0,
                       K=first.truth.K, b=first.truth.b)
        cols = dict(seg.track.columns)
        cols["t"] = cols["t"] + done
        parts.append(cols)
        done += min(seconds - done, 3600.0)
    track = Track({n: np.concatenate([p[n] for p in parts]) for n in parts[0]},
                  first.track.metadata)
    track.write(path)
    return len(track)


#: Run in a fresh, small process: the replay is its only child, so its RUSAGE_CHILDREN is the
#: replay's peak alone (a child forked from this big process would inherit our peak in ru_maxrss).
_MEASURE = """
import resource, subprocess, sys, json
proc = subprocess.run([sys.executable, "-m", "streamcal", *sys.argv[1:]],
                      capture_output=True, text=True)
print(json.dumps({"rc": proc.returncode, "maxrss_kib":
                  resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,
                  "last": proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else "",
                  "stderr": proc.stderr[-2000:]}))
"""


def _replay(path: Path, command: list[str] | None = None) -> tuple[float, int, str]:
    """Run ``streamcal COMMAND`` (default ``replay PATH --json``); (wall s, peak KiB, last line)."""
    import json

    command = command or ["replay", str(path), "--json"]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _MEASURE, *command], capture_output=True,
                          text=True, env=env, check=True)
    elapsed = time.perf_counter() - start
    out = json.loads(proc.stdout)
    if out["rc"] not in (0, 1):
        sys.exit(f"{command[0]} of {path} failed ({out['rc']}): {out['stderr']}")
    return elapsed, out["maxrss_kib"], out["last"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--short-min", type=float, default=5.0)
    ap.add_argument("--long-h", type=float, default=4.0)
    ap.add_argument("--keep", metavar="DIR", help="write the tracks here and keep them")
    ap.add_argument("--only", choices=("replay", "convert-apply"),
                    help="run only the replay rows or only the convert and apply rows")
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
        if args.only != "replay":
            _convert_apply(where, short, long_)
        if args.only == "convert-apply":
            return 0
        t_short, rss_short, s_short = _replay(short)
        print(f"replay short: {t_short:.1f} s, peak RSS {rss_short / 1024:.1f} MiB",
              flush=True)
        t_long, rss_long, s_long = _replay(long_)
        print(f"replay long:  {t_long:.1f} s, peak RSS {rss_long / 1024:.1f} MiB")
        for name, s in (("short", s_short), ("long", s_long)):
            print(f"  {name} summary: {s[:300]}")
        print(f"peak RSS long / short: {rss_long / rss_short:.3f} (target <= 1.15; the file is "
              f"{sizes[long_] / sizes[short]:.0f}x larger)", flush=True)
    return 0


def _convert_apply(where: Path, short: Path, long_: Path) -> None:
    """The convert and apply rows: same tracks, peak RSS long / short."""
    import numpy as np

    from streamcal.calibration import Calibration

    cal = where / "cal.json"
    Calibration(K=np.diag([48.0, 47.0, 49.0]), b=np.array([10.0, -5.0, 3.0]), field=48.0,
                n=1).save(cal)
    for name, make in (("convert", lambda p: ["convert", str(p), "-o", str(p) + ".out.csv.gz"]),
                       ("apply", lambda p: ["apply", str(cal), str(p), "-o",
                                            str(p) + ".applied.csv"])):
        peaks = {}
        for label, path in (("short", short), ("long", long_)):
            seconds, peaks[label], last = _replay(path, make(path))
            print(f"{name} {label + ':':<6} {seconds:.1f} s, peak RSS {peaks[label] / 1024:.1f} "
                  f"MiB ({last[:120]})", flush=True)
        print(f"{name} peak RSS long / short: {peaks['long'] / peaks['short']:.3f} "
              "(target <= 1.15)", flush=True)


if __name__ == "__main__":
    sys.exit(main())
