"""Time and peak RSS of ``streamcal diagnose`` on long tracks: the subsampled path against the
full computation, same run (issue #13 item 2).

    python tools/bench_long_diagnose.py [--keep DIR] [--full-long] [--only 1h,4h]
                                        [--formats] [--baseline CHECKOUT] [--repeat N]

Simulates 5-minute, 1-hour and 4-hour 100 Hz tracks with ``streamcal.sim.simulate`` (hourly
segments of one sensor model and one hidden ``temperature_offset`` placed end to end, two outlier
bursts per segment), writes them once (``--keep`` reuses them), then runs each diagnosis in its
own subprocess (``python -m streamcal diagnose TRACK --json``, peak RSS from
``RUSAGE_CHILDREN`` of a small fresh parent). Baselines in the same run: the full diagnosis
(``--full``) of the 5-minute track, and of the 1-hour track with ``--full-long``. Targets:
1-hour ≤ 10 s and ≤ 400 MB; 4-hour peak RSS ≤ 1.3 × the 1-hour's; verdict and top candidate as
the full computation's.

``--formats`` adds the 1-hour recording as CSV.gz, the CSV ``--cal CAL.json``, and the 1-hour
and 4-hour recordings as ArduPilot DataFlash logs (written by the tests' self-made log writer,
``tests/_selfmade_logs.py``: the same readings, IMU rows, a throttle channel and COMPASS_*
parameters), diagnosed as they are and ``--cal log`` (with ``--full-long`` also the full
``--cal log`` computation of the 1-hour log, the same-run baseline); ``--ulog`` the 1-hour
recording as a PX4 ULog. The subsample is decided by the number of samples, whatever the format
or starting point.

``--baseline CHECKOUT`` runs every row with that checkout's code too (another worktree, e.g. the
commit this one branched from), alternating baseline / this ``--repeat`` times (default 1), and
prints medians, spreads and this/baseline ratios of time and peak RSS. ``--only`` picks rows.
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

EFFECT = {"temperature_offset": [0.25, -0.2, -0.5]}


def _make(path: Path, seconds: float, seed: int) -> int:
    import numpy as np

    from streamcal.inputs.track import Track
    from streamcal.sim import simulate

    seg_s = min(seconds, 3600.0)
    first = simulate(seg_s, seed=seed, effects=EFFECT, outlier_bursts=2, noise_uT=0.4)
    parts, done = [first.track.columns], seg_s
    while done < seconds:
        seg = simulate(seg_s, seed=seed + len(parts), effects=EFFECT, outlier_bursts=2,
                       noise_uT=0.4, K=first.truth.K, b=first.truth.b)
        cols = dict(seg.track.columns)
        cols["t"] = cols["t"] + done
        parts.append(cols)
        done += seg_s
    track = Track({n: np.concatenate([p[n] for p in parts]) for n in parts[0]},
                  first.track.metadata)
    track.write(path)
    return len(track)


_MEASURE = """
import resource, subprocess, sys, json
proc = subprocess.run([sys.executable, "-m", "streamcal", "diagnose", *sys.argv[1:], "--json"],
                      capture_output=True, text=True)
print(json.dumps({"rc": proc.returncode, "maxrss_kib":
                  resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,
                  "out": proc.stdout, "stderr": proc.stderr[-2000:]}))
"""


def _flight(track_path: Path):
    """The track's readings as the tests' self-made flight (``tests/_selfmade_logs.py``): IMU
    rows, a throttle channel, six motor outputs, battery volts and amps at 10 Hz."""
    import numpy as np

    sys.path.insert(0, str(REPO / "tests"))
    from _selfmade_logs import FlightSlice

    from streamcal.inputs.track import Track

    track = Track.read(track_path)
    c = track.columns
    imu = np.isfinite(np.asarray(c["ax"]))
    t_mag = np.asarray(track.t_mag)
    t_ch = np.arange(0.0, float(t_mag[-1]), 0.1)
    thr = 0.5 + 0.2 * np.sin(2 * np.pi * t_ch / 60.0)
    return FlightSlice(
        t_mag=t_mag, mag_uT=np.asarray(track.mag), t_imu=np.asarray(c["t"])[imu],
        accel=np.column_stack([np.asarray(c[k])[imu] for k in ("ax", "ay", "az")]),
        gyro=np.column_stack([np.asarray(c[k])[imu] for k in ("gx", "gy", "gz")]),
        temp=np.asarray(c["temp"])[imu], throttle_at_mag=np.interp(t_mag, t_ch, thr),
        t_ch=t_ch, throttle=thr, pwm=np.tile((1100 + 800 * thr)[:, None], (1, 6)),
        volts=np.full(len(t_ch), 15.8), amps=5.0 + 20.0 * thr)


def _dataflash(track_path: Path, out: Path) -> Path:
    """The track as the DataFlash log ArduPilot would write (self-made writer)."""
    flight = _flight(track_path)
    from _selfmade_logs import write_dataflash

    return write_dataflash(out, flight, messages=("IMU", "RCOU", "CURR"))


def _ulog(track_path: Path, out: Path) -> Path:
    """The track as the ULog PX4 would write (self-made writer: sensor_mag, sensor_combined,
    actuator_outputs, battery_status)."""
    flight = _flight(track_path)
    from _selfmade_logs import write_ulog

    return write_ulog(out, flight, topics=("sensor_combined", "actuator_outputs",
                                           "battery_status"))


def _run(path: Path, full: bool, repo: Path = REPO, label: str = "", extra=()) -> dict:
    env = dict(os.environ, PYTHONPATH=str(repo))
    start = time.perf_counter()
    # cwd: ``-m streamcal`` looks in the working directory first
    proc = subprocess.run([sys.executable, "-c", _MEASURE, str(path), *extra,
                           *(["--full"] if full else [])],
                          capture_output=True, text=True, env=env, check=True, cwd=str(repo))
    elapsed = time.perf_counter() - start
    out = json.loads(proc.stdout)
    if out["rc"] != 0:
        sys.exit(f"diagnose of {path} failed ({out['rc']}): {out['stderr']}")
    d = json.loads(out["out"])
    top = d["candidates"][0]["effect"] if d["candidates"] else None
    row = {"track": path.name + (" " + " ".join(extra) if extra else ""),
           "mode": ("full" if full else "auto") + label, "s": elapsed,
           "rss_mb": out["maxrss_kib"] / 1024, "verdict": d["verdict"], "top": top,
           "used": d["samples_used"], "total": d["samples_total"],
           "spans": len(d["outlier_spans"]), "spans_over": d.get("outlier_spans_over", "all")}
    print(f"{row['track']:<22}{row['mode']:<9}{row['s']:>8.1f} s{row['rss_mb']:>9.0f} MiB  "
          f"{row['verdict']:<15}{str(top):<22}{row['used']:>9}/{row['total']:<9}"
          f"{row['spans']:>4} spans over {row['spans_over']}", flush=True)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", metavar="DIR", help="write the tracks here and reuse them")
    ap.add_argument("--full-long", action="store_true", help="also the full 1-hour diagnosis")
    ap.add_argument("--only", help="comma-separated rows: 5min-full,5min,1h-full,1h,4h")
    ap.add_argument("--formats", action="store_true", help="also the 1-hour recording as CSV.gz, "
                    "as DataFlash diagnosed --cal log, and the CSV --cal CAL.json")
    ap.add_argument("--ulog", action="store_true", help="with --formats: also the 1-hour "
                    "recording as a PX4 ULog")
    ap.add_argument("--baseline", metavar="CHECKOUT", help="also run each row with this checkout")
    ap.add_argument("--repeat", type=int, default=1, help="alternations per row (default 1)")
    args = ap.parse_args()
    plan = [("5min", True), ("5min", False)] + ([("1h", True)] if args.full_long else []) + \
        [("1h", False), ("4h", False)]
    if args.only:
        want = set(args.only.split(","))
        plan = [(n, f) for n, f in plan if (f"{n}-full" if f else n) in want]
    with tempfile.TemporaryDirectory(prefix="bench_long_diag_") as tmp:
        where = Path(args.keep or tmp)
        where.mkdir(parents=True, exist_ok=True)
        tracks = {"5min": 300.0, "1h": 3600.0, "4h": 4 * 3600.0}
        paths = {}
        for name in sorted({n for n, _ in plan}, key=list(tracks).index):
            paths[name] = where / f"{name}.csv"
            if not paths[name].exists():
                start = time.perf_counter()
                rows = _make(paths[name], tracks[name], seed=3)
                print(f"simulated {name}: {rows} rows, {paths[name].stat().st_size / 1e6:.0f} MB "
                      f"in {time.perf_counter() - start:.0f} s", flush=True)
        print(f"{'track':<22}{'mode':<9}{'time':>10}{'peak RSS':>13}  {'verdict':<15}"
              f"{'top candidate':<22}{'used/total mag samples':>19}")
        runs: dict = {}
        for name, full in plan:
            key = (name, "full" if full else "sub")
            for _ in range(max(1, args.repeat)):
                if args.baseline:
                    runs.setdefault(key + ("base",), []).append(
                        _run(paths[name], full, Path(args.baseline).resolve(), "/base"))
                runs.setdefault(key + ("this",), []).append(_run(paths[name], full))
        if args.formats and "1h" in paths:
            import gzip
            import shutil

            gz = where / "1h.csv.gz"
            if not gz.exists():
                with open(paths["1h"], "rb") as src, gzip.open(gz, "wb", compresslevel=1) as dst:
                    shutil.copyfileobj(src, dst)
            bins = {}
            for name in ("1h", "4h"):
                if name in paths:
                    bins[name] = where / f"{name}.bin"
                    if not bins[name].exists():
                        start = time.perf_counter()
                        _dataflash(paths[name], bins[name])
                        print(f"wrote {bins[name].name}: "
                              f"{bins[name].stat().st_size / 1e6:.0f} MB in "
                              f"{time.perf_counter() - start:.0f} s", flush=True)
            cal = where / "cal.json"
            if not cal.exists():
                from streamcal import fit
                from streamcal.inputs.track import Track

                fit(Track.read(paths["5min"] if "5min" in paths else paths["1h"])).save(cal)
            plan = [(gz, (), False), (paths["1h"], ("--cal", str(cal)), False)]
            if "1h" in bins:
                plan += [(bins["1h"], (), False), (bins["1h"], ("--cal", "log"), False)]
                if args.full_long:   # same-run baseline: the full computation
                    plan.append((bins["1h"], ("--cal", "log"), True))
            if "4h" in bins:
                plan.append((bins["4h"], ("--cal", "log"), False))
            if args.ulog:
                ulg = where / "1h.ulg"
                if not ulg.exists():
                    _ulog(paths["1h"], ulg)
                plan.append((ulg, (), False))
                if args.full_long:
                    plan.append((ulg, (), True))
            for path, extra, full in plan:
                runs.setdefault((path.name + " ".join(extra), "full" if full else "sub",
                                 "this"), []).append(_run(path, full, extra=extra))
        rows = {k[:2]: v[-1] for k, v in runs.items() if k[2] == "this"}
        if args.baseline:
            import statistics
            print(f"same run, {args.repeat} alternation(s) baseline/this; medians [min-max]:")
            for (name, mode, who), rs in runs.items():
                if who != "this":
                    continue
                base = runs[(name, mode, "base")]
                ts, bs = [r["s"] for r in rs], [r["s"] for r in base]
                ms, mb = [r["rss_mb"] for r in rs], [r["rss_mb"] for r in base]
                print(f"  {name} {mode}: time {statistics.median(bs):.1f} [{min(bs):.1f}-"
                      f"{max(bs):.1f}] -> {statistics.median(ts):.1f} [{min(ts):.1f}-"
                      f"{max(ts):.1f}] s (x{statistics.median(ts) / statistics.median(bs):.2f}); "
                      f"peak RSS {statistics.median(mb):.0f} -> {statistics.median(ms):.0f} MiB "
                      f"(x{statistics.median(ms) / statistics.median(mb):.2f})")
        one, four, base = rows.get(("1h", "sub")), rows.get(("4h", "sub")), \
            rows.get(("5min", "full"))
        if one and base:
            print(f"1 h subsampled: {one['s']:.1f} s (target <= 10), {one['rss_mb']:.0f} MiB "
                  f"(<= 400); = {one['s'] / base['s']:.2f}x time, "
                  f"{one['rss_mb'] / base['rss_mb']:.2f}x RSS of the full 5-min diagnosis")
        if one and four:
            print(f"4 h / 1 h peak RSS: {four['rss_mb'] / one['rss_mb']:.3f} (target <= 1.3)")
        df1, df4 = rows.get(("1h.bin--cal log", "sub")), rows.get(("4h.bin--cal log", "sub"))
        dff = rows.get(("1h.bin--cal log", "full"))
        if df1 and df4:
            print(f"DataFlash --cal log: 1 h {df1['s']:.1f} s, {df1['rss_mb']:.0f} MiB; 4 h / 1 h "
                  f"peak RSS {df4['rss_mb'] / df1['rss_mb']:.3f} (target <= 1.3)")
        ul, ulf = rows.get(("1h.ulg", "sub")), rows.get(("1h.ulg", "full"))
        if ul and ulf:
            print(f"ULog 1 h: verdict and top candidate equal to the full computation's: "
                  f"{(ul['verdict'], ul['top']) == (ulf['verdict'], ulf['top'])}")
        if df1 and dff:
            print(f"DataFlash --cal log 1 h: verdict and top candidate equal to the full "
                  f"computation's: {(df1['verdict'], df1['top']) == (dff['verdict'], dff['top'])}")
        ref = rows.get(("1h", "full"), base)
        if ref:
            # the ULog carries no temperature (self-made writer): compared with its own full run
            same = all((r["verdict"], r["top"]) == (ref["verdict"], ref["top"])
                       for k, v in runs.items()
                       if "--cal" not in k[0] and not k[0].endswith(".ulg") for r in v)
            print(f"verdict and top candidate equal to the full {ref['track']} diagnosis on "
                  f"every track and run: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
