"""The figures against time and covariates: field magnitude and dip angle per sample
(``magnitude``) and the signed residual against time, temperature and each auxiliary channel
(``residuals``)."""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .figure_common import AFTER, INLIER, OUTLIER, shade_spans, stride_index, thin_index
from .figure_data import FigureData, unit_label


# -- magnitude and dip -------------------------------------------------------------------------
def _dip(v: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Angle of ``v`` (N,3) below the plane ⟂ gravity, degrees (accel points up when still)."""
    with np.errstate(invalid="ignore", divide="ignore"):     # zero rows → NaN, not drawn
        up = accel / np.linalg.norm(accel, axis=1, keepdims=True)
        vn = v / np.linalg.norm(v, axis=1, keepdims=True)
        return np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", vn, up), -1, 1))) - 90.0


def magnitude_figure(data: FigureData) -> Figure:
    accel = data.accel
    fig = Figure(figsize=(12, 6.4 if accel is not None else 3.6))
    axes = np.atleast_1d(fig.subplots(2 if accel is not None else 1, 1, sharex=True))
    unit = unit_label(data.unit)
    idx = stride_index(len(data.t))
    t = data.t[idx]
    ax = axes[0]
    ax.plot(t, np.linalg.norm(data.m[idx], axis=1), color="#999999", lw=0.7, label="before: ‖m‖")
    if data.field_after is not None:
        ax.plot(t, data.field_after[idx], color=AFTER, lw=0.8, label="after: ‖calibrated field‖")
        ax.axhline(data.scale, color="k", lw=0.6, ls="--", label=f"field {data.scale:.4g} {unit}")
    ax.set_ylabel(f"field magnitude ({unit})")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    shade_spans(ax, data)
    if accel is not None:
        ax = axes[1]
        calibrated = data.calibration is not None
        raw = data.m[idx] - data.center if calibrated else data.m[idx]
        ax.plot(t, _dip(raw, accel[idx]), color="#999999", lw=0.7,
                label="before (raw minus b)" if calibrated else "raw readings")
        if data.calibration is not None:
            ax.plot(t, _dip(data.directions[idx], accel[idx]), color=AFTER, lw=0.8,
                    label="after calibration")
        ax.set_ylabel("dip angle (°)")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
        shade_spans(ax, data)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("field magnitude per sample" + (" and dip angle (field vs gravity)"
                                                  if accel is not None else ""))
    fig.tight_layout()
    return fig



# -- residuals -----------------------------------------------------------------------------------
def _covariate_keys(data: FigureData) -> list[str]:
    from ..model._common import aux_names

    keys = ["t"] + (["temp"] if "temp" in data.cov and np.ptp(data.cov["temp"]) > 0 else [])
    return keys + [k for k in aux_names(data.cov) if np.ptp(data.cov[k]) > 0]


_LABELS = {"t": "time (s)", "temp": "temperature (°C)"}


def residuals_figure(data: FigureData) -> Figure:
    keys = _covariate_keys(data)
    fig = Figure(figsize=(12, 2.9 * len(keys) + 0.6))
    axes = np.atleast_1d(fig.subplots(len(keys), 1))
    unit = unit_label(data.unit)
    if data.residual is not None:
        y, ylabel = data.residual, f"residual ({unit})"
        by = (data.diagnosis.residual_families.get("sensor") or {}).get("by", {})
    else:
        mag = np.linalg.norm(data.m, axis=1)
        y, ylabel, by = mag - np.median(mag), f"‖m‖ − median ({unit})", {}
    inl, out = thin_index(data.inliers), thin_index(~data.inliers)
    floor = data.diagnosis.noise_floor if data.diagnosis is not None else float("nan")
    for ax, key in zip(axes, keys):
        xv = data.cov[key] if key in data.cov else data.t
        if key == "t":
            shade_spans(ax, data)
        ax.scatter(xv[inl], y[inl], s=2, color=INLIER, alpha=0.3, lw=0, rasterized=True,
                   label="inliers" if data.residual is not None else "readings")
        if len(out):
            ax.scatter(xv[out], y[out], s=8, color=OUTLIER, marker="x", lw=0.7, label="outliers")
        b = by.get(key)
        if b and b.get("edges"):
            edges = np.asarray(b["edges"])
            r = np.array([np.nan if v is None else v for v in b["rms"]])
            ax.stairs(r, edges, baseline=None, color="k", lw=1.4, label="binned rms (±)")
            ax.stairs(-r, edges, baseline=None, color="k", lw=1.4)
        if np.isfinite(floor):
            ax.axhline(floor, color=AFTER, ls="--", lw=1, label=f"noise floor ±{floor:.3g}")
            ax.axhline(-floor, color=AFTER, ls="--", lw=1)
        lim = np.percentile(np.abs(y[data.inliers]), 99.5) if data.inliers.any() else 1.0
        ax.set_ylim(-2.5 * lim, 2.5 * lim)
        ax.set_xlabel(_LABELS.get(key, f"{key} (auxiliary channel)"))
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), fontsize=8, markerscale=3,
                      ncol=len(handles), frameon=False, borderaxespad=0.1)
    title = ("signed residual (distance to the fitted surface) against time and each covariate"
             if data.residual is not None else "field magnitude against time and each covariate "
             "(no fitted model)")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
