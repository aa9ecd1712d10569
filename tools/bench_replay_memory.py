"""Peak memory of ``streamcal replay``, ``convert`` and ``apply`` on a long recording against a
short one, same run.

    python tools/bench_replay_memory.py [--short-min 5] [--long-h 4] [--keep DIR]
        [--only replay|convert-apply] [--before REV] [--repeat N]

Simulates a short (default 5 min) and a long (default 4 h) 100 Hz track with
``streamcal.sim.simulate`` (magnetometer and IMU both at 100 Hz, on interleaved instants), writes
them with ``Track.write`` into a temp dir (the long one as one-hour segments of one sensor model
end to end), then replays each in its own subprocess (``python -m streamcal replay TRACK
--json``) started by a fresh small process that reads ``resource.getrusage(RUSAGE_CHILDREN)
.ru_maxrss`` after it: the replay's own peak resident set (read in this big process, a forked
child's peak would include ours). The same for ``streamcal convert TRACK -o OUT.csv.gz`` and
``streamcal apply CAL.json TRACK -o OUT.csv`` (a fixed calibration). Target: long / short ≤ 1.15
(memory bounded by the chunk and the calibrator's buffers, not by the recording's length).

``--before REV`` also runs every convert and apply row on the code of git revision ``REV``
(``git archive`` into a temp dir, put first on ``PYTHONPATH``), alternating before / after
``--repeat`` times, and prints each ratio's median and range: a change against its baseline
measured in the same run.
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


def _replay(path: Path, command: list[str] | None = None,
            code: Path = REPO) -> tuple[float, int, str]:
    """Run ``streamcal COMMAND`` (default ``replay PATH --json``) from the package under
    ``code``; (wall s, peak KiB, last line)."""
    import json

    command = command or ["replay", str(path), "--json"]
    env = dict(os.environ, PYTHONPATH=str(code))
    start = time.perf_counter()
    # run from ``code``: ``python -m`` puts the working directory first on sys.path, before
    # PYTHONPATH, so another directory's ``streamcal`` would be imported instead
    proc = subprocess.run([sys.executable, "-c", _MEASURE, *command], capture_output=True,
                          text=True, env=env, check=True, cwd=code)
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
    ap.add_argument("--before", metavar="REV",
                    help="also run convert and apply on git revision REV, alternating")
    ap.add_argument("--repeat", type=int, default=1,
                    help="convert/apply measurements per code version (alternated)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_replay_mem_") as tmp:
        where = Path(args.keep or tmp).resolve()      # commands run from the code's directory
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
            _convert_apply(where, short, long_, args.before, args.repeat)
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


def _checkout(rev: str, into: Path) -> Path:
    """The ``streamcal`` package of git revision ``rev`` extracted under ``into``."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "streamcal"],
                             capture_output=True, check=True).stdout
    into.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def _convert_apply(where: Path, short: Path, long_: Path, before: str | None = None,
                   repeat: int = 1) -> None:
    """The convert and apply rows: same tracks, peak RSS long / short; with ``before``, the
    same on that revision's code, alternated ``repeat`` times (median and range printed)."""
    import numpy as np

    from streamcal.calibration import Calibration

    cal = where / "cal.json"
    Calibration(K=np.diag([48.0, 47.0, 49.0]), b=np.array([10.0, -5.0, 3.0]), field=48.0,
                n=1).save(cal)
    codes = {"after": REPO}
    if before:
        codes = {"before": _checkout(before, where / f"code-{before}"), "after": REPO}
    for name, make in (("convert", lambda p: ["convert", str(p), "-o", str(p) + ".out.csv.gz"]),
                       ("apply", lambda p: ["apply", str(cal), str(p), "-o",
                                            str(p) + ".applied.csv"])):
        ratios = {version: [] for version in codes}
        for k in range(repeat):
            for version, code in codes.items():
                peaks = {}
                for label, path in (("short", short), ("long", long_)):
                    seconds, peaks[label], last = _replay(path, make(path), code)
                    print(f"{name} {version if before else ''} #{k + 1} {label + ':':<6} "
                          f"{seconds:.1f} s, peak RSS {peaks[label] / 1024:.1f} MiB "
                          f"({last[:100]})", flush=True)
                ratios[version].append(peaks["long"] / peaks["short"])
        for version, values in ratios.items():
            print(f"{name} {version if before else ''} peak RSS long / short: median "
                  f"{np.median(values):.3f}, range {min(values):.3f}-{max(values):.3f} over "
                  f"{len(values)} (target <= 1.15)", flush=True)

if __name__ == "__main__":
    sys.exit(main())
