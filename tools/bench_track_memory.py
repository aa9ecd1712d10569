"""Peak memory and time of ``Track.read`` of a whole file against its float64 payload.

    python tools/bench_track_memory.py [--hours 1] [--keep DIR]

Simulates a ``--hours`` (default 1 h) 100 Hz magnetometer + IMU track with
``streamcal.sim.simulate`` (IMU at 100 Hz on interleaved instants; hour segments end to end, as
``bench_replay_memory`` does), writes it with ``Track.write`` as ``.csv`` and ``.csv.gz``, then
reads each in a fresh subprocess (``REPEAT`` reads, each in its own process) that measures:

* the peak resident set increase of the read: the process's ``VmHWM`` (peak RSS, from
  ``/proc/self/status``) after ``Track.read(path)`` minus the same value right before it (after
  imports and a small warm-up read of a 1000-row file, so that lazily imported code and numpy's
  first allocations are not counted). ``VmHWM`` rather than ``getrusage().ru_maxrss``: Linux keeps
  ``ru_maxrss`` across ``execve``, so a child of this big process would start with our peak;
  ``VmHWM`` belongs to the child's own address space;
* the read's wall time (``time.perf_counter``).

Memory ratio = RSS increase / payload, payload = rows × columns × 8 bytes (the float64 columns
the reader returns, which stay alive and are part of the increase). Target: ≤ 2.5.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench_common import REPO
from bench_replay_memory import _make

REPEAT = 3

_MEASURE = """
import sys, time, json
from streamcal.inputs import trackio
from streamcal.inputs.track import Track
trackio.SLICE_BYTES = int(sys.argv[3])
def hwm():
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) for l in f if l.startswith("VmHWM:"))
Track.read(sys.argv[2])   # warm-up on a small file: imports and first allocations
before = hwm()
start = time.perf_counter()
track = Track.read(sys.argv[1])
elapsed = time.perf_counter() - start
after = hwm()
print(json.dumps({"rows": len(track), "cols": len(track.columns), "before_kib": before,
                  "after_kib": after, "seconds": elapsed}))
"""


def _one(path: Path, small: Path, slice_bytes: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _MEASURE, str(path), str(small),
                           str(slice_bytes)], capture_output=True, text=True, env=env, check=True)
    return json.loads(proc.stdout)


def _summary(runs: list[dict]) -> dict:
    best = min(runs, key=lambda r: r["seconds"])
    best["seconds_all"] = [r["seconds"] for r in runs]
    best["increase_kib"] = min(r["after_kib"] - r["before_kib"] for r in runs)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--keep", metavar="DIR", help="write the tracks here and keep them")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from streamcal.inputs import trackio
    from streamcal.inputs.track import Track

    with tempfile.TemporaryDirectory(prefix="bench_track_mem_") as tmp:
        where = Path(args.keep or tmp)
        where.mkdir(parents=True, exist_ok=True)
        plain, packed, small = where / "hour.csv", where / "hour.csv.gz", where / "small.csv"
        if not plain.exists():
            start = time.perf_counter()
            rows = _make(plain, 3600 * args.hours, seed=1)
            print(f"simulated {plain.name}: {rows} rows, {plain.stat().st_size / 1e6:.1f} MB "
                  f"in {time.perf_counter() - start:.1f} s", flush=True)
        if not packed.exists():
            Track.read(plain).write(packed)
        if not small.exists():
            Track.read(plain).select(slice(0, 1000)).write(small)
        print(f"{'file':<12} {'slices':>7} {'rows':>8} {'cols':>4} {'payload MiB':>11} "
              f"{'RSS+ MiB':>9} {'ratio':>6} {'read s (best of %d)' % REPEAT:>20}")
        for path in (plain, packed):
            runs: dict = {"whole": [], "sliced": []}
            for _ in range(REPEAT):   # interleaved: the machine's load hits both alike
                runs["whole"].append(_one(path, small, 1 << 62))
                runs["sliced"].append(_one(path, small, trackio.SLICE_BYTES))
            for label, m in ((k, _summary(v)) for k, v in runs.items()):
                _row(path, label, m)
        print("ratio = peak RSS increase of Track.read (VmHWM after - before) / payload "
              "(rows x columns x 8 bytes); target <= 2.5. 'whole' = the data section parsed in "
              f"one slice (the reader before slicing: same-run baseline); 'sliced' = "
              f"{trackio.SLICE_BYTES >> 20} MiB slices (the default)")
    return 0


def _row(path: Path, label: str, m: dict) -> None:
    payload = m["rows"] * m["cols"] * 8
    increase = m["increase_kib"] * 1024
    print(f"{path.name:<12} {label:>7} {m['rows']:>8} {m['cols']:>4} {payload / 2**20:>11.1f} "
          f"{increase / 2**20:>9.1f} {increase / payload:>6.2f} {m['seconds']:>20.2f}  (all: "
          f"{', '.join(f'{s:.2f}' for s in m['seconds_all'])}; file "
          f"{path.stat().st_size / 2**20:.1f} MiB)", flush=True)


if __name__ == "__main__":
    sys.exit(main())
