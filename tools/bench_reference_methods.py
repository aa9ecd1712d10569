"""Median runtime of the reference methods at N = 450 (the paper's Table VI), as ratios to the
algebraic L2 ellipsoid fit measured in the same run on the same data.

    PYTHONPATH=. python tools/bench_reference_methods.py [--n 450] [--repeats 30] [--outliers 0.05] [--seed 0]

Data follow the paper's simulation (§III-B): K = 100 (I + 0.1 ΔK), b = 20 (1 + Δb), σ = 1,
a fraction of samples perturbed by U(−100, 100) per axis (the real sets of Table VI hold
2.6–6.9 % outliers). Each repeat draws new data; every method, and the baseline, times only its
call on the already normalized samples. Kok–Schön's cvxpy problem is built once per process;
that one-off cost is printed separately.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from streamcal.fitting.ellipsoid import ellipsoid_to_model, fit_l2_ellipsoid
from streamcal.fitting.normalize import normalize
from streamcal.fitting.core import reference_method

#: Table VI of the paper (MATLAB, mean seconds on real data), for comparison of the ratios.
PAPER_SECONDS = {"l2_ellipsoid": 0.002, "dorveaux": 0.035, "kok_schon": 3.891,
                 "vasconcelos": 0.014, "magical": 0.032}


def synthetic(rng: np.random.Generator, n: int, outliers: float) -> np.ndarray:
    dk = rng.standard_normal(6)
    K = 100.0 * (np.eye(3) + 0.1 * np.array([[dk[0], dk[1], dk[3]],
                                             [0.0, dk[2], dk[4]],
                                             [0.0, 0.0, dk[5]]]))
    b = 20.0 * (1.0 + rng.standard_normal(3))
    x = rng.standard_normal((n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = x @ K.T + b + rng.standard_normal((n, 3))
    bad = rng.random(n) < outliers
    m[bad] += rng.uniform(-100.0, 100.0, (int(bad.sum()), 3))
    return m


def l2_baseline(m_n: np.ndarray):
    return ellipsoid_to_model(*fit_l2_ellipsoid(m_n))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=450)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--outliers", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    methods = {"l2_ellipsoid": l2_baseline, **{n: reference_method(n) for n in ("magical", "dorveaux", "vasconcelos", "kok_schon")}}
    rng = np.random.default_rng(args.seed)
    warm, _, _ = normalize(synthetic(rng, args.n, args.outliers))
    t0 = time.perf_counter()
    methods["kok_schon"](warm)  # builds and compiles the cvxpy problem
    first_kok = time.perf_counter() - t0
    for fit in methods.values():
        fit(warm)

    seconds = {name: [] for name in methods}
    failures = {name: 0 for name in methods}
    for _ in range(args.repeats):
        m_n, _, _ = normalize(synthetic(rng, args.n, args.outliers))
        for name, fit in methods.items():
            t0 = time.perf_counter()
            try:
                fit(m_n)
            except Exception:  # an L2 method may fail on outlier-laden data; count it
                failures[name] += 1
            seconds[name].append(time.perf_counter() - t0)

    base = float(np.median(seconds["l2_ellipsoid"]))
    paper_base = PAPER_SECONDS["l2_ellipsoid"]
    print(f"N = {args.n}, {args.repeats} repeats, outliers {args.outliers:.0%}; "
          f"baseline (L2 ellipsoid) median {base * 1e3:.3f} ms")
    print(f"{'method':<14}{'median ms':>11}{'ratio':>9}{'paper ratio':>13}{'failures':>10}")
    for name, values in seconds.items():
        median = float(np.median(values))
        paper = PAPER_SECONDS[name] / paper_base
        print(f"{name:<14}{median * 1e3:>11.3f}{median / base:>9.1f}{paper:>13.1f}"
              f"{failures[name]:>10}")
    print(f"kok_schon first call (builds the cvxpy problem): {first_kok * 1e3:.0f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
