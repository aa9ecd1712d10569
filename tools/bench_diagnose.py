"""Benchmark: diagnosing a 5-minute 100 Hz track (accel, gyro, temperature, motor current) with
every candidate, beside a plain fit of the same track timed in the same run.

    python tools/bench_diagnose.py [--duration 300] [--seed 0]

Target: diagnosis ≤ 10 s. Prints the plain fit, the diagnosis as shipped (warm-started refits,
candidates ranked on a spread subset of ``SUBSET_MAX`` samples, winner refitted on all) and, as
the baseline measured in the same run, the diagnosis refitting every candidate on every sample
(``subset_max=None``), warm-started and cold (every refit from stage 1, as before); with ``--registration`` the registration candidates are timed too
(they are skipped by default to compare with the earlier 19.5 s figure, which lacked them).

Then the same track without its accelerometer columns (a mag + gyro recording) with a hidden
time_lag, diagnosed with every candidate: time_lag is then judged on the gyro-tied residual
(:mod:`streamcal.fitting.gyro_lag`); its time is reported beside the shipped diagnosis above.
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
    parser.add_argument("--registration", action="store_true",
                        help="include mag_accel_misalignment and time_lag among the candidates")
    args = parser.parse_args()

    from streamcal.diagnosis import diagnose
    from streamcal.sim import simulate
    from tests._diagnose_helpers import fitter

    track = simulate(args.duration, args.seed, effects={"temperature_offset": 0.5}).track
    t0 = time.perf_counter()
    fitter(track, ("hard_iron", "soft_iron"))
    t_fit = time.perf_counter() - t0
    from streamcal.diagnosis.diagnosis import SUBSET_MAX, _candidate_names

    names = [n for n in _candidate_names(("hard_iron", "soft_iron"), track)
             if args.registration or n not in ("mag_accel_misalignment", "time_lag")]
    runs = {}
    def cold(track_, model):  # no ``initial``: every refit starts from stage 1 (as before)
        return fitter(track_, model)

    for label, fit_, subset in (("cold, full (baseline)", cold, None),
                                ("warm, full", fitter, None),
                                (f"shipped (subset {SUBSET_MAX})", fitter, SUBSET_MAX)):
        t0 = time.perf_counter()
        d = diagnose(track, fitter=fit_, candidates=names, subset_max=subset)
        runs[label] = (time.perf_counter() - t0, d)
    print(f"track: {args.duration:.0f} s, {d.n} magnetometer samples, "
          f"{len(d.candidates)} candidates, ladder of {len(d.ladder)} steps")
    print(f"plain fit   {t_fit:8.2f} s")
    base_t = runs["cold, full (baseline)"][0]
    for label, (t, d) in runs.items():
        print(f"diagnosis, {label:<24} {t:8.2f} s   ({t / t_fit:.1f} × the fit, "
              f"{t / base_t:.2f} × baseline; target ≤ 10 s: {'met' if t <= 10 else 'NOT met'})")
        print("    " + ", ".join(f"{c.effect} {c.rms_after:.3f}" for c in d.candidates[:4]))
    print(f"verdict {d.verdict}, top candidate {d.candidates[0].effect if d.candidates else '-'}")
    shipped_t = runs[f"shipped (subset {SUBSET_MAX})"][0]

    from streamcal.inputs.track import Track

    lagged = simulate(args.duration, args.seed, effects={"time_lag": 0.02}).track
    gyro_only = Track({k: v for k, v in lagged.columns.items() if k not in ("ax", "ay", "az")},
                      lagged.metadata)
    t0 = time.perf_counter()
    d = diagnose(gyro_only, fitter=fitter, subset_max=SUBSET_MAX)
    t_gyro = time.perf_counter() - t0
    top = d.candidates[0] if d.candidates else None
    print(f"gyro-only track, hidden time_lag 20 ms, every candidate: {t_gyro:8.2f} s   "
          f"({t_gyro / t_fit:.1f} × the fit, {t_gyro / shipped_t:.2f} × the shipped diagnosis "
          f"above; target ≤ 10 s: {'met' if t_gyro <= 10 else 'NOT met'})")
    if top is not None:
        print(f"    verdict {d.verdict}, top {top.effect} {top.rms_after:.3f}: {top.evidence}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
