"""autocal against the oracle under heavy contamination, with and without the mixture polish.

    python tools/bench_contamination.py [--seeds 0:200] [--sigma 1] [--eta 0.3] [--zeta 100]

Data: ``streamcal.sim.paper_protocol`` (σ_K = 100, σ_b = 20, N = 1000, a fraction η of samples
shifted by U(−ζ, ζ) per axis), one data set per seed of the stated range. On each data set,
alternating in the same run:

- ``autocal`` — ``fit`` as it runs by default (with the mixture polish of
  ``streamcal.fitting.mixture_polish`` where the stage-1 diagnostics flag outliers);
- ``without`` — the same code with the mixture polish replaced by the identity (the baseline);
- ``ORACLE`` — the L2 LM on the inliers only (``bench_paper_protocol.py``'s oracle);
- ``ORACLE+3σ`` — the L2 LM on the inliers plus the outliers within 3σ of the TRUE surface.

Reported: the ratio of mean normalized errors (eq. 39) to the oracle's (the figure
``bench_paper_protocol.py`` checks), its 95 % bootstrap interval over seeds (2,000 resamples),
the ratio on each half of the seed range, and the median of per-seed ratios.
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from _bench_common import normalized_error, run_stamp

import streamcal.fitting.autocal as autocal_module
from streamcal.fitting import fit
from streamcal.fitting.ellipsoid import directions_from_model
from streamcal.sim import paper_protocol

COLUMNS = ("autocal", "without", "ORACLE+3σ")


def _identity(result, sigma, refine_with):
    return result, sigma


def run(seeds, sigma: float, eta: float, zeta: float, n: int = 1000):
    """Errors (len(seeds), 4): ORACLE, autocal, without, ORACLE+3σ; and seconds per fit."""
    polish = autocal_module.mixture_polish
    rows, secs = [], {"autocal": 0.0, "without": 0.0}
    for seed in seeds:
        m, K, b, inl = paper_protocol(n, sigma, eta, seed, zeta=zeta)
        x = directions_from_model(K, b, m)
        near = np.linalg.norm(x @ K.T + b - m, axis=1) <= 3 * sigma
        row = [normalized_error(*_kb(fit(m[inl], kernel="l2", check_coverage=False)), K, b)]
        for name in ("autocal", "without") if seed % 2 == 0 else ("without", "autocal"):
            autocal_module.mixture_polish = polish if name == "autocal" else _identity
            try:
                t0 = time.perf_counter()
                cal = fit(m, check_coverage=False)
                secs[name] += time.perf_counter() - t0
            finally:
                autocal_module.mixture_polish = polish
            row.append((name, normalized_error(*_kb(cal), K, b)))
        row = [row[0]] + [e for _, e in sorted(row[1:], key=lambda t: COLUMNS.index(t[0]))]
        row.append(normalized_error(*_kb(fit(m[inl | near], kernel="l2", check_coverage=False)), K, b))
        rows.append(row)
    return np.asarray(rows), {k: v / len(seeds) for k, v in secs.items()}


def _kb(cal):
    return cal.K, cal.b


def ratio_summary(err: np.ndarray, col: int, boot: int = 2000, seed: int = 0) -> dict:
    """Mean-error ratio of column ``col`` to column 0 with its bootstrap interval over rows."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(err), (boot, len(err)))
    b = err[idx, col].mean(axis=1) / err[idx, 0].mean(axis=1)
    h = len(err) // 2
    return {"ratio": err[:, col].mean() / err[:, 0].mean(),
            "lo": float(np.percentile(b, 2.5)), "hi": float(np.percentile(b, 97.5)),
            "half1": err[:h, col].mean() / err[:h, 0].mean(),
            "half2": err[h:, col].mean() / err[h:, 0].mean(),
            "median": float(np.median(err[:, col] / err[:, 0]))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="0:200", help="seed range start:stop (default 0:200)")
    p.add_argument("--sigma", type=float, default=1.0)
    p.add_argument("--eta", type=float, default=0.30)
    p.add_argument("--zeta", type=float, default=100.0)
    args = p.parse_args(argv)
    lo, hi = (int(v) for v in args.seeds.split(":"))
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    err, secs = run(range(lo, hi), args.sigma, args.eta, args.zeta)
    print(run_stamp())
    print(f"\nσ = {args.sigma:g}, η = {args.eta:.0%}, ζ = {args.zeta:g}, N = 1000, seeds {lo}–{hi - 1} "
          f"({hi - lo} data sets); {time.perf_counter() - t0:.0f} s\n")
    print("| fit | mean error % | mean/ORACLE [95 % bootstrap] | first half | second half "
          "| median per-seed ratio | s/fit |")
    print("|---|---|---|---|---|---|---|")
    print(f"| ORACLE | {100 * err[:, 0].mean():.4f} | 1 | | | | |")
    for col, name in enumerate(COLUMNS, start=1):
        s = ratio_summary(err, col)
        per = f"{secs[name]:.4f}" if name in secs else ""
        print(f"| {name} | {100 * err[:, col].mean():.4f} | {s['ratio']:.3f} [{s['lo']:.3f}, "
              f"{s['hi']:.3f}] | {s['half1']:.3f} | {s['half2']:.3f} | {s['median']:.3f} | {per} |")
    d = err[:, 1] - err[:, 2]
    print(f"\nautocal − without, per seed: better on {(d < 0).sum()}, worse on {(d > 0).sum()}, "
          f"equal on {(d == 0).sum()} of {len(d)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
