#!/usr/bin/env python3
"""Benchmark of the streaming calibrator, reported as ratios to baselines measured in the same run.

1. Ingest cost per sample, one sample per ``ingest`` call (target ≤ 10 µs) — baseline: a Python
   loop copying the same rows one at a time into a numpy array.
2. Ingest throughput in blocks of 100, 1000 and 10 000 samples (target ≥ 1 M samples/s) —
   baseline: ``np.copy`` of the same data.
   Both include the fits (sphere fitter on a worker thread) and report the process CPU time too:
   on a machine shared with other jobs, CPU time is the steadier figure. Run with
   ``OPENBLAS_NUM_THREADS=1``: BLAS threads on 6×n products cost more than they save.
3. A synthetic 1-hour 100 Hz replay with refits (target ≤ 10 s) and its peak RSS against a
   5-minute replay (target within 10 %); each replay runs in a fresh subprocess so that
   ``ru_maxrss`` is its own.

    python tools/bench_stream.py [--quick] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def synthetic(duration_s: float, rate: float = 100.0, seed: int = 0, start_s: float = 0.0):
    """Board turning through every direction every two minutes; soft + hard iron, noise (µT)."""
    t = start_s + np.arange(0.0, duration_s, 1.0 / rate)
    th = np.pi * (0.5 - 0.5 * np.cos(2 * np.pi * t / 120.0))       # pole to pole and back
    ph = 2 * np.pi * t / 4.0
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    K = np.array([[50.0, 1.5, -0.8], [0.0, 47.0, 1.2], [0.0, 0.0, 53.0]])
    rng = np.random.default_rng(seed)
    return t, d @ K.T + [12.0, -25.0, 40.0] + rng.normal(scale=0.4, size=d.shape)


def _fitter(name):
    from streamcal.stream.fitworker import default_fitter

    if name == "sphere":
        from streamcal.calibration import Calibration
        from streamcal.fitting.sphere_stream import fit_sphere_stream

        def sphere(snap):
            K, b = fit_sphere_stream(snap.m)
            r = np.linalg.norm(snap.m - b, axis=1) - K[0, 0]
            return Calibration(K=K, b=b, rms=float(np.sqrt(np.mean(r ** 2))), n=len(snap.m))
        return sphere
    return default_fitter()


def bench_single(n: int) -> dict:
    from streamcal.samples import SampleBlock
    from streamcal.stream import StreamingCalibrator

    t, m = synthetic(n / 100.0)
    blocks = [SampleBlock(t=t[i:i + 1], mag=m[i:i + 1]) for i in range(len(t))]
    sc = StreamingCalibrator(fitter=_fitter("sphere"))
    start, cpu = time.perf_counter(), time.process_time()
    for block in blocks:
        sc.ingest(block)
    sc.close()
    cost = (time.perf_counter() - start) / len(blocks)
    cpu = (time.process_time() - cpu) / len(blocks)
    dst = np.empty_like(m)
    start = time.perf_counter()
    for i, block in enumerate(blocks):
        dst[i] = block.mag[0]
    base = (time.perf_counter() - start) / len(blocks)
    return {"single_us_per_sample": cost * 1e6, "single_cpu_us_per_sample": cpu * 1e6,
            "single_baseline_us": base * 1e6,
            "single_ratio_to_baseline": cost / base, "single_target_us": 10.0}


def bench_batched(n: int, block: int) -> dict:
    from streamcal.samples import SampleBlock
    from streamcal.stream import StreamingCalibrator

    t, m = synthetic(n / 100.0)
    blocks = [SampleBlock(t=t[i:i + block], mag=m[i:i + block]) for i in range(0, len(t), block)]
    sc = StreamingCalibrator(fitter=_fitter("sphere"))
    start, cpu = time.perf_counter(), time.process_time()
    for b in blocks:
        sc.ingest(b)
    sc.close()
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu
    start = time.perf_counter()
    for b in blocks:
        np.copy(b.mag)
    base = time.perf_counter() - start
    return {"batched_block": block, "batched_samples_per_s": len(t) / elapsed,
            "batched_us_per_sample": elapsed / len(t) * 1e6,
            "batched_cpu_samples_per_s": len(t) / cpu,
            "batched_baseline_samples_per_s": len(t) / base,
            "batched_ratio_to_baseline": elapsed / base, "batched_target_samples_per_s": 1e6}


def replay_child(duration_s: float, block: int, fitter: str) -> dict:
    """One replay in this process: wall time, fits, peak RSS (run in a subprocess)."""
    from streamcal.samples import SampleBlock
    from streamcal.stream import StreamingCalibrator

    sc = StreamingCalibrator(fitter=_fitter(fitter))
    t, m = synthetic(0.01)
    sc.ingest(SampleBlock(t=t, mag=m))                  # imports and first-call setup
    kinds: dict[str, int] = {}
    start = time.perf_counter()
    # The input is generated a minute at a time so that its memory does not grow with duration.
    for k, chunk_start in enumerate(np.arange(0.01, duration_s, 60.0)):
        t, m = synthetic(min(60.0, duration_s - chunk_start), seed=k, start_s=chunk_start)
        for i in range(0, len(t), block):
            for e in sc.ingest(SampleBlock(t=t[i:i + block], mag=m[i:i + block])):
                kinds[e.kind] = kinds.get(e.kind, 0) + 1
    for e in sc.close():
        kinds[e.kind] = kinds.get(e.kind, 0) + 1
    elapsed = time.perf_counter() - start
    return {"duration_s": duration_s, "wall_s": elapsed, "events": kinds,
            "maxrss_kB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
            "b": sc.calibration.b.tolist() if sc.calibration is not None else None}


def _run_child(duration_s, block, fitter) -> dict:
    code = (f"import sys, json; sys.path.insert(0, {str(REPO)!r}); "
            f"sys.path.insert(0, {str(REPO / 'tools')!r}); import bench_stream as b; "
            f"print(json.dumps(b.replay_child({duration_s}, {block}, {fitter!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_replay(block: int, fitter: str, hour_s: float) -> dict:
    long = _run_child(hour_s, block, fitter)
    short = _run_child(300.0, block, fitter)
    return {"replay_hour_wall_s": long["wall_s"], "replay_hour_target_s": 10.0,
            "replay_hour_events": long["events"], "replay_5min_wall_s": short["wall_s"],
            "replay_hour_samples_per_s": hour_s * 100.0 / long["wall_s"],
            "peak_rss_hour_MB": long["maxrss_kB"] / 1024,
            "peak_rss_5min_MB": short["maxrss_kB"] / 1024,
            "peak_rss_ratio": long["maxrss_kB"] / short["maxrss_kB"],
            "peak_rss_target_ratio": 1.10, "final_b_hour": long["b"], "fitter": fitter}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smaller sizes (smoke test)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--fitter", choices=("default", "sphere"), default="default",
                   help="fitter for the replays: streamcal.fitting.fit (default) or the sphere fit")
    args = p.parse_args()
    n_single = 5_000 if args.quick else 50_000
    n_batch = 200_000 if args.quick else 1_000_000
    results = {}
    results.update(bench_single(n_single))
    for block in (100, 1000, 10_000):
        r = bench_batched(n_batch, block)
        results.update({f"{k}@{block}": v for k, v in r.items() if k != "batched_block"})
    results.update(bench_replay(100, args.fitter, 600.0 if args.quick else 3600.0))
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        for key, value in results.items():
            print(f"{key:40s} {value:.4g}" if isinstance(value, float) else f"{key:40s} {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
