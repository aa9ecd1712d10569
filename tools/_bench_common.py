"""Helpers shared by the ``tools/bench_*`` scripts: the paper's error metrics, the Cramér–Rao
bound of the core model, timing, real-track loading and the run stamp printed above each table.
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

SHARED = Path(os.environ.get("STREAMCAL_SHARED", REPO.parent / "shared"))
#: The real recordings (not in the repository): ``STREAMCAL_SHARED``, as for the tests.
REAL_DATA = SHARED / "data" / "real"
REAL_TRACKS = REAL_DATA / "tracks"
REAL_FLIGHTS = REAL_DATA / "flight"


def normalized_error(K, b, K_ref, b_ref) -> float:
    """Paper eq. 39/40: ‖[K b] − [K_ref b_ref]‖_F / ‖[K_ref b_ref]‖_F (dimensionless)."""
    A = np.column_stack([np.asarray(K, float), np.asarray(b, float)])
    R = np.column_stack([np.asarray(K_ref, float), np.asarray(b_ref, float)])
    return float(np.linalg.norm(A - R) / np.linalg.norm(R))


def fisher_core(K: np.ndarray, x: np.ndarray, sigma: float) -> np.ndarray:
    """Fisher information (9,9) of p = (K11 K12 K13 K22 K23 K33, b1 b2 b3) for
    m_j = K x_j + b + N(0, σ² I) with the unit directions x_j (N,3) as nuisance parameters.

    Built as the Schur complement of the L2 Gauss–Newton matrix at the true model and true
    directions, each x_j parametrised by two tangent coordinates (basis T_j, 3×2):

        J_pj = ∂r_j/∂p (3×9),  J_xj = K T_j (3×2)
        F = (1/σ²) Σ_j J_pjᵀ J_pj − J_pjᵀ J_xj (J_xjᵀ J_xj)⁻¹ J_xjᵀ J_pj
    """
    x = np.asarray(x, float)
    n = len(x)
    entries = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    Jp = np.zeros((n, 3, 9))
    for col, (i, j) in enumerate(entries):
        Jp[:, i, col] = x[:, j]
    Jp[:, :, 6:] = np.eye(3)
    # tangent basis: e × x normalised, with e the axis least aligned with x; then x × t1
    e = np.eye(3)[np.argmin(np.abs(x), axis=1)]
    t1 = np.cross(e, x)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(x, t1)
    T = np.stack([t1, t2], axis=2)                         # (N,3,2)
    Jx = np.asarray(K, float)[None] @ T                    # (N,3,2)
    Hpp = np.einsum("nip,niq->pq", Jp, Jp)
    Hpx = np.einsum("nip,nia->npa", Jp, Jx)                # (N,9,2)
    Hxx = np.einsum("nia,nib->nab", Jx, Jx)                # (N,2,2)
    S = Hpp - np.einsum("npa,nab,nqb->pq", Hpx, np.linalg.inv(Hxx), Hpx)
    return S / sigma ** 2


def crlb_normalized(K, b, x, sigma) -> float:
    """√trace(F⁻¹) / ‖[K b]‖_F: the bound on the RMS of the normalized model error (eq. 39)."""
    cov = np.linalg.inv(fisher_core(K, x, sigma))
    return float(np.sqrt(np.trace(cov)) / np.linalg.norm(np.column_stack([K, b])))


def run_stamp(argv=None) -> str:
    """One line: date (UTC), git commit, host, numpy/BLAS threads, and the command line."""
    commit = os.environ.get("STREAMCAL_BENCH_COMMIT")  # set when run from an exported snapshot
    try:
        commit = commit or subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True, timeout=5).stdout.strip()
    except Exception:  # no git: the stamp is informative only
        commit = "?"
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    threads = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    cmd = " ".join(["python"] + [str(a) for a in (sys.argv if argv is None else argv)])
    return (f"{now}, commit {commit}, {platform.machine()} {os.cpu_count()} CPUs, "
            f"python {platform.python_version()}, numpy {np.__version__}, "
            f"OPENBLAS_NUM_THREADS={threads}\n$ {cmd}")


def median_seconds(fn, repeats: int, warmup: int = 1) -> float:
    """Median wall time (s) of ``fn()`` over ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def real_track(name: str):
    """Read ``tracks/<name>.csv[.gz]`` from the shared real-data folder (a Track)."""
    from streamcal.inputs.track import Track

    for suffix in (".csv", ".csv.gz"):
        path = REAL_TRACKS / f"{name}{suffix}"
        if path.exists():
            return Track.read(path)
    raise FileNotFoundError(f"no track {name!r} in {REAL_TRACKS} (set STREAMCAL_SHARED)")


def fmt_pct(v: float, digits: int = 2) -> str:
    return "fail" if v is None or not np.isfinite(v) else f"{100 * v:.{digits}f}%"
