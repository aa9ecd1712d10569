"""Paired timing of ``streamcal.fit`` in two source trees, for before/after figures of a change.

    python tools/bench_compare_trees.py BEFORE_TREE AFTER_TREE [--rounds 6]

Each round runs one fresh process per tree (order alternating), each timing the median of 31
default fits of the first 1,000 rows of ``freeimucal_mag_data.txt`` after 10 warm-up fits; the
figure is the median over rounds of the per-round ratio after ÷ before. A second table times
the LM alone, µs per sample·iteration: ``refine`` with the Geman–McClure kernel, 5 iterations
from the algebraic start of a clean paper-protocol track (σ = 1), at N = 1000 and 1e5, with the
numpy engine and the compiled one (where it applies in that tree: numba before the C engine,
the built extension after). Pairing matters on a
shared machine whose speed drifts within minutes: the two trees of a round ran back to back, so
their ratio is steadier than either time. A tree is a checkout or an exported commit
(``git worktree add /tmp/before <commit>``); each process imports streamcal from its tree.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numpy as np

from _bench_common import SHARED

PROBE = r"""
import sys, time
import numpy as np
from streamcal.fitting import fit
m = np.loadtxt(sys.argv[1], max_rows=1000, usecols=(0, 1, 2))
for _ in range(10):
    fit(m)
times = []
for _ in range(31):
    t = time.perf_counter()
    fit(m)
    times.append(time.perf_counter() - t)
print(np.median(times))
try:
    from streamcal.fitting import lm_compiled
    print("C-built" if lm_compiled.available() else "C-not-built")
except ImportError:                             # a tree from before the C engine
    print("no-C-engine")
import streamcal
print(streamcal.__file__)
"""

LM_PROBE = r"""
import time
import numpy as np
from streamcal.fitting import ellipsoid, lm
from streamcal.fitting.kernels import make_kernel
from streamcal.fitting.normalize import normalize
from streamcal.sim import paper_protocol
for n in (1000, 100_000):
    m_n = normalize(paper_protocol(n, 1.0, 0.0, 1)[0])[0]
    K, b = ellipsoid.ellipsoid_to_model(*ellipsoid.fit_l2_ellipsoid(m_n))
    x = ellipsoid.directions_and_residuals(K, b, m_n)[0]
    for engine in ("numpy", "compiled"):
        def run():
            return lm.refine(m_n, K, b, x, kernel=make_kernel("gm", 0.02), max_iter=5, rtol=0.0,
                             engine=engine)
        try:
            res = run()
        except ValueError:                      # the compiled engine does not apply in this tree
            print(n, engine, "nan")
            continue
        times = []
        for _ in range(15 if n == 1000 else 3):
            t = time.perf_counter()
            run()
            times.append(time.perf_counter() - t)
        print(n, engine, np.median(times) / res.iterations / n * 1e6)
"""


def _env(tree: str) -> dict:
    """The probe's environment: the tree first on the path, one BLAS thread, and no engine
    choice inherited from the caller (each tree runs its own default)."""
    env = {**os.environ, "PYTHONPATH": os.path.abspath(tree), "OPENBLAS_NUM_THREADS": "1"}
    env.pop("STREAMCAL_LM_ENGINE", None)
    return env


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("before")
    p.add_argument("after")
    p.add_argument("--rounds", type=int, default=6)
    args = p.parse_args()
    data = str(SHARED / "data" / "real" / "freeimucal_mag_data.txt")
    times = {args.before: [], args.after: []}
    built = {}
    for r in range(args.rounds):
        for tree in (args.before, args.after) if r % 2 == 0 else (args.after, args.before):
            out = subprocess.run([sys.executable, "-c", PROBE, data], env=_env(tree), cwd="/", check=True,
                                 capture_output=True, text=True).stdout.split()
            if not out[-1].startswith(os.path.abspath(tree)):   # not the tree's own streamcal
                raise SystemExit(f"{tree}: streamcal was imported from {out[-1]}")
            times[tree].append(float(out[-3]))
            built[tree] = out[-2]
    before, after = np.array(times[args.before]), np.array(times[args.after])
    ratio = after / before
    print(f"freeimucal N = 1000, streamcal.fit default, {args.rounds} paired rounds")
    print(f"  extension: before {built[args.before]}, after {built[args.after]}")
    print(f"  before {args.before}: median {np.median(before) * 1e3:.2f} ms "
          f"(rounds {' '.join(f'{v * 1e3:.2f}' for v in before)})")
    print(f"  after  {args.after}: median {np.median(after) * 1e3:.2f} ms "
          f"(rounds {' '.join(f'{v * 1e3:.2f}' for v in after)})")
    print(f"  after ÷ before: median {np.median(ratio):.3f} (rounds {ratio.min():.3f}–{ratio.max():.3f})")
    print("\nLM alone, µs per sample·iteration (GM kernel, 5 iterations from the algebraic start), "
          "two alternated rounds")
    lm_times: dict = {}
    for r in range(2):
        for tree in (args.before, args.after) if r % 2 == 0 else (args.after, args.before):
            out = subprocess.run([sys.executable, "-c", LM_PROBE], env=_env(tree), cwd="/", check=True,
                                 capture_output=True, text=True).stdout
            for line in out.splitlines():
                n, engine, value = line.split()
                lm_times.setdefault((tree, n, engine), []).append(float(value))
    print("| tree | N | numpy engine | compiled engine |\n|---|---|---|---|")
    for tree in (args.before, args.after):
        for n in ("1000", "100000"):
            cells = [" / ".join(f"{v:.3f}" for v in lm_times[tree, n, e]) for e in ("numpy", "compiled")]
            print(f"| {tree} | {n} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
