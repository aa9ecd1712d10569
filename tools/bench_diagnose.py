"""Benchmark: diagnosing a 5-minute 100 Hz track (accel, gyro, temperature, motor current) with
every candidate, beside a plain fit of the same track timed in the same run.

    python tools/bench_diagnose.py [--duration 300] [--seed 0]

Target: diagnosis ≤ 10 s. Prints both times and their ratio.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=300.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from streamcal.diagnose import diagnose
    from streamcal.sim import simulate
    from tests._diagnose_helpers import fitter

    track = simulate(args.duration, args.seed, effects={"temperature_offset": 0.5}).track
    t0 = time.perf_counter()
    fitter(track, ("hard_iron", "soft_iron"))
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = diagnose(track, fitter=fitter)
    t_diag = time.perf_counter() - t0
    print(f"track: {args.duration:.0f} s, {d.n} magnetometer samples, "
          f"{len(d.candidates)} candidates, ladder of {len(d.ladder)} steps")
    print(f"plain fit   {t_fit:8.2f} s")
    print(f"diagnosis   {t_diag:8.2f} s   ({t_diag / t_fit:.1f} × the fit; target ≤ 10 s: "
          f"{'met' if t_diag <= 10 else 'NOT met'})")
    print(f"verdict {d.verdict}, top candidate "
          f"{d.candidates[0].effect if d.candidates else '-'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
