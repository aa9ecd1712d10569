"""Where the misfit sits: the residual energy of a model split over time, field direction,
covariate ranges and rotation rate (docs/cli.md ``misfit``, given with the ``unexplained`` verdict).

Energy is ``Σ‖r_j‖²`` over the inliers the rms is over (so ``rms² = energy / n``). Each
grouping partitions those samples into bins; a bin reports its ``share`` of the energy and its
``samples`` share (fraction of the inliers). Shares of one grouping sum to 1; a bin whose
energy share far exceeds its sample share is where the model fails. ``excess`` =
share / samples (1 for a misfit spread evenly).
"""
from __future__ import annotations

import numpy as np

from ..constants import ATTITUDE_COLUMNS

#: Equal-duration time bins.
TIME_BINS = 10
#: Quantile bins per covariate.
COVARIATE_BINS = 4
#: Rotation-rate bin edges (rad/s).
RATE_EDGES = (0.0, 0.1, 0.5, 1.5, np.inf)
#: Covariates not treated as such (time, the gyro has its own grouping).
_NOT_COVARIATES = {"t", "gx", "gy", "gz", *ATTITUDE_COLUMNS}  # quaternion parts: no ranges
#: Direction cells: the nearest of the six body axes.
_AXES = np.vstack([np.eye(3), -np.eye(3)])
_AXIS_NAMES = ("+X", "+Y", "+Z", "-X", "-Y", "-Z")


def _bins(labels: np.ndarray, energy: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    e = np.bincount(labels, weights=energy, minlength=n_bins)
    c = np.bincount(labels, minlength=n_bins).astype(float)
    total_e, total_c = e.sum(), c.sum()
    return (e / total_e if total_e > 0 else np.zeros(n_bins),
            c / total_c if total_c > 0 else np.zeros(n_bins))


def _entries(share, samples, describe) -> list[dict]:
    out = []
    for k, (s, c) in enumerate(zip(share, samples)):
        if c == 0:
            continue
        out.append({**describe(k), "share": float(s), "samples": float(c),
                    "excess": float(s / c)})
    return out


def _quantile_labels(v: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    edges = np.unique(np.quantile(v, np.linspace(0, 1, n_bins + 1)))
    if len(edges) < 2:
        edges = np.array([v.min(), v.max()])
    labels = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    return labels, edges


#: Half-window (s) over which the field direction's turning rate is measured: long enough
#: that the noise's jitter of the direction (≈ σ/|B| per sample) does not pass for rotation.
RATE_HALF_WINDOW_S = 0.1


def rotation_rate(t: np.ndarray, directions: np.ndarray, gyro: np.ndarray | None = None
                  ) -> tuple[np.ndarray, str]:
    """Rotation rate (N,) rad/s: ‖gyro‖ when given, else the angle between the field directions
    (N,3 unit) :data:`RATE_HALF_WINDOW_S` before and after each sample over the time between
    them (at least one sample each side); and where it comes from."""
    if gyro is not None and np.all(np.isfinite(gyro)):
        return np.linalg.norm(gyro, axis=1), "gyro"
    n = len(t)
    if n < 3:
        return np.zeros(n), "field direction"
    k = max(1, int(round(RATE_HALF_WINDOW_S / max(float(np.median(np.diff(t))), 1e-9))))
    k = min(k, (n - 1) // 2)
    lo = np.clip(np.arange(n) - k, 0, n - 1)
    hi = np.clip(np.arange(n) + k, 0, n - 1)
    cosang = np.clip(np.sum(directions[hi] * directions[lo], axis=1), -1.0, 1.0)
    dt = t[hi] - t[lo]
    return np.arccos(cosang) / np.where(dt > 0, dt, np.inf), "field direction"


def localise(r: np.ndarray, inliers: np.ndarray, t: np.ndarray, directions: np.ndarray,
             cov: dict | None = None, gyro: np.ndarray | None = None) -> dict:
    """Split the residual energy of ``r`` (N,3, or (N,) norms) over the ``inliers`` (N,) bool.

    Args:
        t: (N,) sample times (s).
        directions: (N,3) field directions in the sensor frame (need not be unit).
        cov: covariates at the samples (name → (N,)), e.g. ``temp``.
        gyro: (N,3) rad/s, optional (else the rate comes from the field direction).

    Returns ``{"time": […], "directions": […], "covariates": {name: […]}, "rotation_rate":
    {"source": …, "bins": […]}, "energy": Σ‖r‖², "n": inliers}``; each bin has ``share``,
    ``samples``, ``excess`` and what it covers (``t`` [s, s], ``axis``, ``range``, ``rad_s``).
    """
    r = np.asarray(r, dtype=float)
    e_all = np.sum(r * r, axis=1) if r.ndim == 2 else r * r
    t = np.asarray(t, dtype=float)
    if len(e_all) != len(t):   # a residual not per sample (gyro-tied pairs)
        return {"energy": float(np.nansum(e_all)), "n": int(len(e_all))}
    keep = np.asarray(inliers, bool) & np.isfinite(e_all)
    e = e_all[keep]
    out: dict = {"energy": float(e.sum()), "n": int(keep.sum())}
    if not keep.any():
        return out
    tk = t[keep]
    t0, t1 = float(tk.min()), float(tk.max())
    width = (t1 - t0) / TIME_BINS or 1.0
    lab = np.clip(((tk - t0) / width).astype(int), 0, TIME_BINS - 1)
    out["time"] = _entries(*_bins(lab, e, TIME_BINS),
                           lambda k: {"t": [t0 + k * width, t0 + (k + 1) * width]})
    d = np.asarray(directions, dtype=float)[keep]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    lab = np.argmax(d @ _AXES.T, axis=1)
    out["directions"] = _entries(*_bins(lab, e, 6), lambda k: {"axis": _AXIS_NAMES[k]})
    out["covariates"] = {}
    for name, v in sorted((cov or {}).items()):
        v = np.asarray(v, dtype=float)
        if name in _NOT_COVARIATES or v.shape != t.shape:
            continue
        vk = v[keep]
        if not np.all(np.isfinite(vk)) or np.ptp(vk) == 0:
            continue
        lab, edges = _quantile_labels(vk, COVARIATE_BINS)
        out["covariates"][name] = _entries(
            *_bins(lab, e, len(edges) - 1),
            lambda k, edges=edges: {"range": [float(edges[k]), float(edges[k + 1])]})
    rate, source = rotation_rate(t, np.asarray(directions, dtype=float) / np.maximum(
        np.linalg.norm(directions, axis=1, keepdims=True), 1e-300), gyro)
    edges = np.asarray(RATE_EDGES)
    lab = np.clip(np.searchsorted(edges, rate[keep], side="right") - 1, 0, len(edges) - 2)
    out["rotation_rate"] = {"source": source, "bins": _entries(
        *_bins(lab, e, len(edges) - 1),
        lambda k: {"rad_s": [float(edges[k]), float(edges[k + 1]) if np.isfinite(edges[k + 1])
                             else None]})}
    return out


def _where(b: dict) -> str:
    if "t" in b:
        return f"{b['t'][0]:.1f}–{b['t'][1]:.1f} s"
    if "axis" in b:
        return f"field along {b['axis']}"
    if "range" in b:
        return f"{b['range'][0]:.3g}–{b['range'][1]:.3g}"
    lo, hi = b["rad_s"]
    return f"{lo:g}–{hi:g} rad/s" if hi is not None else f"above {lo:g} rad/s"


def summary(misfit: dict) -> list[str]:
    """One line per grouping: the bin with the largest excess, its energy and sample shares."""
    groups = [("time", misfit.get("time") or [])]
    groups.append(("direction", misfit.get("directions") or []))
    for name, bins in (misfit.get("covariates") or {}).items():
        groups.append((name, bins))
    rr = misfit.get("rotation_rate") or {}
    if rr.get("bins"):
        groups.append((f"rotation rate ({rr['source']})", rr["bins"]))
    lines = []
    for label, bins in groups:
        if not bins:
            continue
        top = max(bins, key=lambda b: b["excess"])
        lines.append(f"{label:<32} {100 * top['share']:5.1f}% of the residual energy in "
                     f"{100 * top['samples']:5.1f}% of the samples ({_where(top)})")
    return lines
