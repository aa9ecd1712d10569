"""Figures of a diagnosis: what the model sees, where it fails, and what fixes it.

Every figure is drawn on its own :class:`matplotlib.figure.Figure` with the Agg canvas (no
``pyplot``, no global backend switch, safe in threads and on a machine without a display) and
saved as PNG with the software/date metadata removed, so the same inputs give the same bytes.
Large tracks are thinned with a fixed stride for the scatter plots (every outlier is kept).

The figures (names are the PNG file names without ``.png``):

- ``ellipsoid``: raw readings in three orthogonal projections with the fitted surface
  ``m = K x + b`` (‖x‖ = 1) as a wireframe, inliers and outliers marked (autocalibration paper,
  Fig. 1/7 top).
- ``magnitude``: ‖m‖ before and ‖calibrated field‖ after calibration per sample, and the angle
  between the field and gravity (dip) before/after when the track has an accelerometer (Fig. 7
  bottom).
- ``coverage``: the sphere of field directions on two Lambert azimuthal equal-area discs (the
  hemispheres around +Z and −Z), cut into the equal-area cells of
  :class:`streamcal.stream.sphere_cells.SphereCells`; each seen cell coloured by the rms residual of
  its samples, empty cells grey, the largest empty cap marked.
- ``residuals``: the signed residual (distance to the fitted surface along its normal) against
  time, temperature and each auxiliary channel, with the binned rms of the diagnosis and the
  noise floor; outlier spans shaded on the time axis.
- ``ladder``: rms after each effect the ladder added, the noise floor as a line, and every
  candidate's promised ``rms_after`` — each against the model without it *on the same
  residual*: the sensor residual (eq. 41) and the gravity- and gyro-tied residuals of the
  registration effects are different scales (:data:`RESIDUAL_FAMILIES`), so each gets its own
  panel, its own "model now" line and its own noise level, and the ladder marks where it
  switches residual.

When the fit refused the track (:class:`~streamcal.errors.InsufficientDataError`) the figures
show what does not need a calibration: raw readings, ‖m‖, and coverage seen from the centre of a
one-pass sphere fit.
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from ..constants import HALF_NORMAL_MEDIAN
from ..diagnosis.diagnosis import RESIDUAL_LABELS

#: Most points drawn per scatter series (a fixed stride thins the rest).
MAX_POINTS = 5000
#: Equal-area cells of the coverage map (same partition as the streaming coverage buffer).
COVERAGE_CELLS = 300
DPI = 100
_PNG_METADATA = {"Software": None}
_INLIER, _OUTLIER, _FIT, _AFTER = "#1f5fa8", "#d62728", "#444444", "#2ca02c"
_SPAN = "#f4b6b6"
_AXES = ("x", "y", "z")


def unit_label(unit: str) -> str:
    """Display form of a sensor unit (``uT`` → ``µT``): :func:`streamcal.units.display_unit`."""
    from ..units import display_unit

    return display_unit(unit)


@dataclass
class FigureData:
    """Per-sample views of a track and its diagnosis, shared by every figure.

    Attributes (N magnetometer samples):
        t: (N,) s. m: (N,3) readings, sensor unit. cov: covariates at the samples {name: (N,)}.
        unit: sensor unit. diagnosis: the :class:`~streamcal.diagnose.Diagnosis` or None.
        reason: why there is no diagnosis (the fit's refusal), else None.
        inliers: (N,) bool: not the diagnosis' ``outliers`` (the model ``outliers_model``, the
        one its ``n_outliers`` and spans come from), else the calibration's.
        directions: (N,3) unit field directions (calibrated, or from the coarse sphere when
        refused). residual: (N,) signed distance to the fitted surface along
        its outward normal, sensor unit (None when refused). field_after: (N,) ‖calibrated
        field‖, sensor unit (None when refused). scale: field strength used, sensor unit.
    """

    t: np.ndarray
    m: np.ndarray
    cov: dict
    unit: str
    diagnosis: object = None
    reason: str | None = None
    inliers: np.ndarray = None
    directions: np.ndarray = None
    residual: np.ndarray | None = None
    field_after: np.ndarray | None = None
    scale: float = float("nan")
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def calibration(self):
        return None if self.diagnosis is None else self.diagnosis.calibration

    @property
    def accel(self) -> np.ndarray | None:
        if all(k in self.cov for k in ("ax", "ay", "az")):
            return np.stack([self.cov["ax"], self.cov["ay"], self.cov["az"]], axis=1)
        return None

    @classmethod
    def build(cls, track, diagnosis=None, reason: str | None = None) -> "FigureData":
        """Views of ``track`` (:class:`streamcal.inputs.track.Track`) with ``diagnosis`` (or, when
        None, the raw data only, ``reason`` saying why)."""
        m = np.asarray(track.mag, dtype=float)
        cov = {k: np.asarray(v, dtype=float) for k, v in track.covariates_at_mag().items()}
        t = cov.get("t", np.asarray(track.t_mag, dtype=float))
        data = cls(t=t, m=m, cov=cov, unit=track.mag_unit, diagnosis=diagnosis, reason=reason)
        cal = data.calibration
        if cal is None:
            data._coarse()
        else:
            data._calibrated(cal)
        return data

    def _calibrated(self, cal) -> None:
        from ..diagnosis.diagnosis import OUTLIER_SIGMAS
        from ..diagnosis.residuals import sensor_residual

        r, x, s, _ = sensor_residual(cal, self.m, self.cov)
        # The diagnosis' outliers (its n_outliers and spans, one model) when it has them.
        out = getattr(self.diagnosis, "outliers", None)
        inl = ~np.asarray(out, bool) if out is not None and np.shape(out) == (len(self.m),) \
            else getattr(cal, "inliers", None)
        if inl is None or np.shape(inl) != (len(self.m),):
            floor = self.diagnosis.noise_floor
            norm = np.linalg.norm(r, axis=1)
            scale = floor if np.isfinite(floor) else np.median(norm) / HALF_NORMAL_MEDIAN
            inl = norm <= OUTLIER_SIGMAS * scale
        self.inliers = np.asarray(inl, bool)
        self.directions, self.residual = x, s
        self.scale = float(cal.field or cal.radius)
        self.field_after = np.linalg.norm(cal.apply(self.m, self.cov), axis=1) * self.scale
        self.center = np.asarray(cal.b, dtype=float)

    def _coarse(self) -> None:
        from ..fitting.sphere_stream import SphereStats

        stats = SphereStats()
        stats.update(self.m)
        try:
            center, radius = stats.fit()
        except Exception:   # fewer than 4 samples or degenerate: centre on the median
            center = np.median(self.m, axis=0) if len(self.m) else np.zeros(3)
            radius = float("nan")
        d = self.m - center
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        self.directions = d / np.where(norm > 0, norm, 1.0)
        self.inliers = np.ones(len(self.m), bool)
        self.center, self.scale = np.asarray(center, float), float(radius)


@dataclass(frozen=True)
class RenderedFigure:
    """One figure: ``name`` (file stem), ``title``, ``caption`` (what it shows) and ``png``
    bytes."""

    name: str
    title: str
    caption: str
    png: bytes


def _stride(n: int, limit: int = MAX_POINTS) -> np.ndarray:
    return np.arange(n) if n <= limit else np.unique(np.linspace(0, n - 1, limit).astype(int))


def _thin(mask: np.ndarray, limit: int = MAX_POINTS) -> np.ndarray:
    idx = np.flatnonzero(mask)
    return idx[_stride(len(idx), limit)]


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata=_PNG_METADATA)
    return buf.getvalue()


def _note(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=10,
            color="#555555", wrap=True)
    ax.set_xticks([])
    ax.set_yticks([])


# -- ellipsoid ---------------------------------------------------------------------------------
def _wireframe(K: np.ndarray, b: np.ndarray, n_lines: int = 12, n_points: int = 60):
    """Lines (list of (n_points,3)) on the surface ``K x + b``, ‖x‖ = 1: meridians and
    parallels."""
    s = np.linspace(0, 2 * np.pi, n_points)
    lines = []
    for phi in np.linspace(0, np.pi, n_lines // 2, endpoint=False):
        u = np.stack([np.cos(s) * np.cos(phi), np.cos(s) * np.sin(phi), np.sin(s)], axis=1)
        lines.append(u @ K.T + b)
    for z in np.linspace(-0.9, 0.9, n_lines // 2 + 1):
        rho = np.sqrt(1 - z * z)
        u = np.stack([rho * np.cos(s), rho * np.sin(s), np.full_like(s, z)], axis=1)
        lines.append(u @ K.T + b)
    return lines


def ellipsoid_figure(data: FigureData) -> Figure:
    fig = Figure(figsize=(12, 4.2))
    axes = fig.subplots(1, 3)
    unit = unit_label(data.unit)
    cal = data.calibration
    lines = _wireframe(cal.K, cal.b) if cal is not None else []
    inl, out = _thin(data.inliers), _thin(~data.inliers)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        for line in lines:
            ax.plot(line[:, i], line[:, j], color=_FIT, lw=0.6, alpha=0.55)
        ax.scatter(data.m[inl, i], data.m[inl, j], s=2, color=_INLIER, alpha=0.35, lw=0,
                   rasterized=True, label=(f"inliers ({int(data.inliers.sum())})" if cal is not None
                                           else f"readings ({len(data.m)})"))
        if len(out):
            ax.scatter(data.m[out, i], data.m[out, j], s=10, color=_OUTLIER, marker="x", lw=0.8,
                       label=f"outliers ({int((~data.inliers).sum())})")
        ax.set_xlabel(f"m{_AXES[i]} ({unit})")
        ax.set_ylabel(f"m{_AXES[j]} ({unit})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, markerscale=3)
    fig.suptitle("raw readings and the fitted ellipsoid (wireframe)" if cal is not None
                 else "raw readings (no fitted model: the fit was refused)")
    fig.tight_layout()
    return fig


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
    idx = _stride(len(data.t))
    t = data.t[idx]
    ax = axes[0]
    ax.plot(t, np.linalg.norm(data.m[idx], axis=1), color="#999999", lw=0.7, label="before: ‖m‖")
    if data.field_after is not None:
        ax.plot(t, data.field_after[idx], color=_AFTER, lw=0.8, label="after: ‖calibrated field‖")
        ax.axhline(data.scale, color="k", lw=0.6, ls="--", label=f"field {data.scale:.4g} {unit}")
    ax.set_ylabel(f"field magnitude ({unit})")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    _shade_spans(ax, data)
    if accel is not None:
        ax = axes[1]
        calibrated = data.calibration is not None
        raw = data.m[idx] - data.center if calibrated else data.m[idx]
        ax.plot(t, _dip(raw, accel[idx]), color="#999999", lw=0.7,
                label="before (raw minus b)" if calibrated else "raw readings")
        if data.calibration is not None:
            ax.plot(t, _dip(data.directions[idx], accel[idx]), color=_AFTER, lw=0.8,
                    label="after calibration")
        ax.set_ylabel("dip angle (°)")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
        _shade_spans(ax, data)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("field magnitude per sample" + (" and dip angle (field vs gravity)"
                                                  if accel is not None else ""))
    fig.tight_layout()
    return fig


def _shade_spans(ax, data: FigureData) -> None:
    spans = data.diagnosis.outlier_spans if data.diagnosis is not None else []
    for k, (a, b) in enumerate(spans):
        ax.axvspan(a, b, color=_SPAN, alpha=0.6, lw=0, label="outlier span" if k == 0 else None)


# -- coverage ------------------------------------------------------------------------------------
def cell_polygons(cells, north: bool, n_arc: int = 8):
    """Polygons (list of (k,2)) of the cells of ``cells`` (:class:`SphereCells`) in the
    hemisphere around +Z (``north``) or −Z, Lambert azimuthal equal-area coordinates (radius √2
    at the equator), seen from outside; and the cell index of each."""
    polys, ids = [], []
    for band, count in enumerate(cells.counts):
        z_hi, z_lo = cells.z_edges[band], cells.z_edges[band + 1]
        if (z_lo < -1e-12) if north else (z_hi > 1e-12):
            continue                     # band of the other hemisphere
        width = 2 * np.pi / count
        for j in range(count):
            phi = -np.pi + width * np.array([j, j + 1])
            arc = np.linspace(phi[0], phi[1], n_arc)
            near, far = (z_hi, z_lo) if north else (z_lo, z_hi)
            r_near = np.sqrt(max(0.0, 2 * (1 - abs(near))))
            r_far = np.sqrt(max(0.0, 2 * (1 - abs(far))))
            pts = np.concatenate([np.stack([r_far * np.cos(arc), r_far * np.sin(arc)], 1),
                                  np.stack([r_near * np.cos(arc[::-1]), r_near * np.sin(arc[::-1])], 1)])
            if not north:
                pts[:, 1] = -pts[:, 1]
            polys.append(pts)
            ids.append(cells.offsets[band] + j)
    return polys, np.asarray(ids)


def lambert(d: np.ndarray, north: bool) -> np.ndarray:
    """Lambert azimuthal equal-area coordinates (n,2) of unit directions ``d`` (n,3) on the disc
    of the +Z (``north``) or −Z hemisphere, seen from outside."""
    z = d[:, 2] if north else -d[:, 2]
    rho = np.sqrt(np.clip(2 * (1 - z), 0, None))
    h = np.hypot(d[:, 0], d[:, 1])
    h = np.where(h > 0, h, 1.0)
    xy = np.stack([rho * d[:, 0] / h, rho * d[:, 1] / h], axis=1)
    if not north:
        xy[:, 1] = -xy[:, 1]
    return xy


def coverage_cells(data: FigureData, n_cells: int = COVERAGE_CELLS):
    """Cells, per-cell sample count (C,), per-cell rms residual over inliers (C,) (NaN: no
    inlier), the covered fraction, and the largest empty cap (centre (3,), radius °)."""
    from ..stream.sphere_cells import SphereCells, largest_empty_cap

    cells = SphereCells(n_cells)
    ok = np.isfinite(data.directions).all(axis=1)
    idx = cells.cell_of(data.directions[ok])
    count = np.bincount(idx, minlength=cells.n_cells)
    rms = np.full(cells.n_cells, np.nan)
    if data.residual is not None:
        sel = data.inliers[ok]
        n = np.bincount(idx[sel], minlength=cells.n_cells)
        ss = np.bincount(idx[sel], weights=data.residual[ok][sel] ** 2, minlength=cells.n_cells)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.where(n > 0, np.sqrt(ss / np.maximum(n, 1)), np.nan)
    thin = data.directions[ok][_stride(int(ok.sum()), 4000)]
    center, radius = largest_empty_cap(thin)
    return cells, count, rms, float((count > 0).mean()), center, radius


def coverage_figure(data: FigureData) -> Figure:
    import matplotlib
    from matplotlib import cm, colors

    from ..stream.sphere_cells import hint

    cells, count, rms, fraction, gap_c, gap_r = coverage_cells(data)
    fig = Figure(figsize=(12, 5.4))
    axes = fig.subplots(1, 2)
    fig.subplots_adjust(left=0.02, right=0.86, bottom=0.02, top=0.84, wspace=0.05)
    floor = data.diagnosis.noise_floor if data.diagnosis is not None else float("nan")
    finite = rms[np.isfinite(rms)]
    vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
    if np.isfinite(floor):
        vmax = max(vmax, 2.0 * floor)
    norm = colors.Normalize(0.0, vmax)
    cmap = matplotlib.colormaps["viridis"]
    unit = unit_label(data.unit)
    for ax, north in zip(axes, (True, False)):
        polys, ids = cell_polygons(cells, north)
        face = []
        for c in ids:
            if count[c] == 0:
                face.append("#e4e4e4")
            elif data.residual is None:
                face.append(_INLIER)
            elif np.isfinite(rms[c]):
                face.append(cmap(norm(rms[c])))
            else:
                face.append(_OUTLIER)           # seen only in outliers
        ax.add_collection(PolyCollection(polys, facecolors=face, edgecolors="white", linewidths=0.6))
        edge = np.linspace(0, 2 * np.pi, 200)
        ax.plot(np.sqrt(2) * np.cos(edge), np.sqrt(2) * np.sin(edge), color="#888888", lw=0.8)
        sign = 1 if north else -1
        for text, (x, y) in (("+X", (1, 0)), ("−X", (-1, 0)), ("+Y", (0, sign)), ("−Y", (0, -sign))):
            ax.text(1.62 * x, 1.62 * y, text, ha="center", va="center", fontsize=10)
        if (gap_c[2] >= 0) == north and gap_r >= 20:
            p = lambert(gap_c[None, :], north)[0]
            ax.plot(*p, marker="x", color="k", ms=12, mew=2)
            ax.annotate(f"largest gap ({gap_r:.0f}°)", p, xytext=(8, 8), textcoords="offset points",
                        fontsize=9)
        ax.set_xlim(-1.85, 1.85)
        ax.set_ylim(-1.85, 1.85)
        ax.set_aspect("equal")
        ax.axis("off")
        ax.set_title("field from the top half (+Z), seen from above" if north
                     else "field from the underside (−Z), seen from below", fontsize=10)
    if data.residual is not None:
        sm = cm.ScalarMappable(norm=norm, cmap=cmap)
        bar = fig.colorbar(sm, cax=fig.add_axes((0.88, 0.12, 0.018, 0.62)))
        label = f"rms residual per cell ({unit})"
        if np.isfinite(floor):
            bar.ax.axhline(floor, color="w", lw=2)
            label += "; white line: noise floor"
        bar.set_label(label)
    seen = int((count > 0).sum())
    if data.calibration is not None:
        second = _wrap(hint(gap_c, gap_r, fraction), 140)
    else:
        second = ("approximate: directions seen from the centre of a one-pass sphere fit, "
                  "because the full fit was refused")
    fig.suptitle(f"coverage of the sphere of field directions: {100 * fraction:.0f}% "
                 f"({seen}/{cells.n_cells} equal-area cells; grey = never seen)\n" + second,
                 fontsize=10)
    return fig


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


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
    inl, out = _thin(data.inliers), _thin(~data.inliers)
    floor = data.diagnosis.noise_floor if data.diagnosis is not None else float("nan")
    for ax, key in zip(axes, keys):
        xv = data.cov[key] if key in data.cov else data.t
        if key == "t":
            _shade_spans(ax, data)
        ax.scatter(xv[inl], y[inl], s=2, color=_INLIER, alpha=0.3, lw=0, rasterized=True,
                   label="inliers" if data.residual is not None else "readings")
        if len(out):
            ax.scatter(xv[out], y[out], s=8, color=_OUTLIER, marker="x", lw=0.7, label="outliers")
        b = by.get(key)
        if b and b.get("edges"):
            edges = np.asarray(b["edges"])
            r = np.array([np.nan if v is None else v for v in b["rms"]])
            ax.stairs(r, edges, baseline=None, color="k", lw=1.4, label="binned rms (±)")
            ax.stairs(-r, edges, baseline=None, color="k", lw=1.4)
        if np.isfinite(floor):
            ax.axhline(floor, color=_AFTER, ls="--", lw=1, label=f"noise floor ±{floor:.3g}")
            ax.axhline(-floor, color=_AFTER, ls="--", lw=1)
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


# -- ladder ----------------------------------------------------------------------------------------
#: The residual families an rms of the diagnosis can be on (``Diagnosis.residual``,
#: ``candidate_baselines``, ladder ``residual``): (label, what it is, colour, noise alone as a
#: multiple of the noise floor). The floor is the noise along one axis, which the sensor
#: residual keeps (eq. 41: the free direction absorbs the two tangent components); with the
#: direction tied to gravity only the heading is free, so two components stay (√2 × floor) and
#: the gravity reference's own error adds to that; the gyro-tied residual compares two samples,
#: two components each (≈ 2 × floor, :mod:`streamcal.fitting.gyro_lag`).
RESIDUAL_FAMILIES = {
    "sensor": (f"{RESIDUAL_LABELS['sensor']} residual", "every direction free (eq. 41)",
               _INLIER, 1.0),
    "gravity_tied": (f"{RESIDUAL_LABELS['gravity_tied']} residual",
                     "directions tied to gravity, includes the accelerometer's error",
                     "#8c4fbf", float(np.sqrt(2.0))),
    "gyro_tied": (f"{RESIDUAL_LABELS['gyro_tied']} residual",
                  "directions carried 0.5 s ahead by the gyro", "#e07b00", 2.0),
}
_FLOOR_TEXT = {"sensor": "noise floor", "gravity_tied": "noise alone ≈ √2×floor",
               "gyro_tied": "noise alone ≈ 2×floor"}


def _family(name) -> str:
    return name if name in RESIDUAL_FAMILIES else "sensor"


def ladder_steps(d) -> list[dict]:
    """The ladder of ``d`` with, for every step, ``residual`` (family of its rms) and, after the
    first, ``rms_before``: the previous model on the same residual (it differs from the previous
    step's rms where the ladder switches to a tied residual)."""
    steps = d.ladder or [{"model": list(d.model), "rms": d.rms}]
    out = []
    for k, step in enumerate(steps):
        step = dict(step)
        # diagnose names every step's residual; a hand-made ladder without it is on the base
        # model's residual first, then on the sensor residual
        step["residual"] = _family(step.get("residual", d.residual if k == 0 else "sensor"))
        if k and "rms_before" not in step:
            step["rms_before"] = out[-1]["rms"]
        out.append(step)
    return out


def candidate_groups(d) -> list[tuple[str, float, list]]:
    """Candidates of ``d`` grouped by the residual their ``rms_after`` is on, in order of first
    appearance in the ranking: ``[(residual, rms_before, [candidate, …]), …]`` — each group's
    rms_before is the model without the effect on that residual, what its bars compare with."""
    groups: dict[str, tuple[float, list]] = {}
    for c in d.candidates:
        residual, before = d.baseline(c)
        residual = _family(residual)
        groups.setdefault(residual, (before, []))[1].append(c)
    return [(name, before, cands) for name, (before, cands) in groups.items()]


def relative_change(before: float, after: float) -> str:
    """Relative change ``after / before − 1`` as text ("−39 %", "±0 %")."""
    if not (before > 0 and np.isfinite(after)):
        return ""
    pct = round(100.0 * (after / before - 1.0))
    return "±0 %" if pct == 0 else f"{'+' if pct > 0 else '−'}{abs(pct)} %"


def _ladder_panel(ax, d, unit: str) -> None:
    steps = ladder_steps(d)
    floor = d.noise_floor
    k_all = np.arange(len(steps))
    tops = [s["rms"] for s in steps] + [s.get("rms_before", 0.0) for s in steps]
    for k, step in enumerate(steps):
        label, _, colour, _ = RESIDUAL_FAMILIES[step["residual"]]
        ax.plot(k, step["rms"], "o", color=colour, ms=8, zorder=3)
        ax.annotate(f"{step['rms']:.3g}", (k, step["rms"]), xytext=(8, 4),
                    textcoords="offset points", fontsize=9, color=colour)
        if not k:
            continue
        prev, before = steps[k - 1], step["rms_before"]
        if prev["residual"] != step["residual"]:   # same model, another residual: say so
            ax.plot([k - 1, k - 1], [prev["rms"], before], ":", color="#777777", lw=1.2)
            ax.plot(k - 1, before, "o", mfc="white", mec=colour, mew=1.8, ms=8, zorder=3)
            ax.annotate(f"same model on the {label}: {before:.3g}", (k - 1, before),
                        xytext=(8, 4), textcoords="offset points", fontsize=8, color=colour)
        ax.plot([k - 1, k], [before, step["rms"]], "-", color=colour, lw=2)
        ax.annotate(relative_change(before, step["rms"]), ((k - 0.5), (before + step["rms"]) / 2),
                    xytext=(4, 4), textcoords="offset points", ha="left", va="bottom", fontsize=9,
                    color=colour, fontweight="bold")
    families = list(dict.fromkeys(s["residual"] for s in steps))
    if np.isfinite(floor):
        for fam in families:
            label, _, colour, factor = RESIDUAL_FAMILIES[fam]
            level = factor * floor
            ax.axhline(level, color=_AFTER if fam == "sensor" else colour,
                       ls="--" if fam == "sensor" else ":", lw=1.5,
                       label=f"{_FLOOR_TEXT[fam]} {level:.3g} {unit}")
            tops.append(level)
    for fam in families:   # legend entry per residual family
        label, what, colour, _ = RESIDUAL_FAMILIES[fam]
        ax.plot([], [], "o-", color=colour, label=label)
    ax.legend(loc="upper right", fontsize=7)
    names = [", ".join(s["model"]) if "added" not in s else "+ " + s["added"] for s in steps]
    ax.set_xticks(k_all, names, rotation=12, fontsize=8)
    ax.set_xlim(-0.5, len(steps) - 0.3)
    top_finite = np.nanmax(np.asarray(tops, float)) if np.isfinite(tops).any() else np.nan
    ax.set_ylim(0, 1.5 * top_finite if top_finite > 0 else 1.0)   # an rms over no inliers is NaN
    ax.set_ylabel(f"rms residual ({unit})")
    ax.set_title("model ladder: rms after each added effect\n(colour: the residual; each step "
                 "from the last model on it)", fontsize=10)
    ax.grid(alpha=0.3)


def _candidate_panel(ax, d, residual: str, before: float, cands: list, unit: str,
                     first: bool) -> None:
    label, what, colour, factor = RESIDUAL_FAMILIES[residual]
    after = np.array([c.rms_after for c in cands], dtype=float)
    y = np.arange(len(cands))[::-1]
    ax.barh(y, after, color=[_AFTER if c.significant else "#bbbbbb" for c in cands],
            height=0.7)
    ax.set_yticks(y, [c.effect for c in cands], fontsize=8)
    now = "model now" if residual == d.residual else "same model"
    ax.axvline(before, color="k", lw=1.2)
    top = ax.get_xaxis_transform()
    ax.text(before, 1.01, f"{now} {before:.3g}", transform=top, ha="center", va="bottom",
            fontsize=8)
    values = list(after) + [before]
    if np.isfinite(d.noise_floor):
        level = factor * d.noise_floor
        ax.axvline(level, color=_AFTER if residual == "sensor" else colour,
                   ls="--" if residual == "sensor" else ":", lw=1.5)
        values.append(level)
    finite = np.asarray(values, float)[np.isfinite(values)]
    xmax = 1.32 * finite.max() if finite.size and finite.max() > 0 else 1.0
    if np.isfinite(d.noise_floor):   # text left of the line, or right of it near the axis
        left = level > 0.25 * xmax
        ax.text(level, 0.02, (_FLOOR_TEXT[residual] + " ") if left else
                (" " + _FLOOR_TEXT[residual]), transform=top, ha="right" if left else "left",
                va="bottom", fontsize=7, color=_AFTER if residual == "sensor" else colour)
    ax.set_xlim(0, xmax)
    right = ax.get_yaxis_transform()
    for yi, c, a in zip(y, cands, after):
        worse = a > before * 1.005
        ax.text(0.995, yi, f"{a:.3g}  {relative_change(before, a)}", transform=right, ha="right",
                va="center", fontsize=8, color=_OUTLIER if worse else
                (_AFTER if c.significant else "#555555"),
                fontweight="bold" if c.significant else "normal")
    ax.set_ylim(-0.6, len(cands) - 0.4)
    ax.set_xlabel(f"rms after adding it ({unit}), {label}", fontsize=8)
    ax.tick_params(axis="x", labelsize=8)
    ax.grid(alpha=0.3, axis="x")
    title = f"{label}: {what}"
    if first:
        title = "candidate effects, best first (green = significant; % = change)\n" + title
    ax.set_title(title, fontsize=9, color=colour, pad=14)


def ladder_figure(data: FigureData) -> Figure:
    """Left: the model ladder, each step against the previous model on its own residual.
    Right: one panel per residual family (:data:`RESIDUAL_FAMILIES`), each candidate's
    ``rms_after`` against the model without it on the same residual ("model now" / "same
    model") and that residual's noise level, with the relative change."""
    d = data.diagnosis
    unit = unit_label(data.unit)
    groups = candidate_groups(d)
    rows = [len(c) + 2.2 for _, _, c in groups] or [1.0]
    fig = Figure(figsize=(12, max(4.4, 0.9 + 0.3 * sum(rows))))
    gs = fig.add_gridspec(len(rows), 2, width_ratios=[1, 1.3], height_ratios=rows)
    _ladder_panel(fig.add_subplot(gs[:, 0]), d, unit)
    if not groups:
        ax = fig.add_subplot(gs[0, 1])
        _note(ax, "no candidate effect can be tried on this track")
        ax.set_title("candidate effects, best first", fontsize=10, pad=16)
    for i, (residual, before, cands) in enumerate(groups):
        _candidate_panel(fig.add_subplot(gs[i, 1]), d, residual, before, cands, unit, i == 0)
    fig.tight_layout()
    return fig


#: (name, title, caption, function, needs a diagnosis)
FIGURES = (
    ("ellipsoid", "Raw readings and the fitted ellipsoid",
     "Three orthogonal projections of the raw magnetometer readings. A calibrated sensor's "
     "readings lie on the ellipsoid m = K x + b; points far from the wireframe are outliers "
     "(red), points spread around it show what the model misses.", ellipsoid_figure, False),
    ("magnitude", "Field magnitude and dip angle",
     "Before calibration the field magnitude swings with the orientation; after it, it should "
     "stay at the local field strength, and the dip (angle between field and gravity) should be "
     "constant. What is left is error the model does not explain (or motion, for the dip).",
     magnitude_figure, False),
    ("coverage", "Coverage of the sphere of directions",
     "Each equal-area cell of the sphere of field directions, coloured by the rms residual of "
     "the samples that fell in it. Grey cells were never seen: turn the sensor so the field "
     "arrives from there. Cells brighter than the rest show where the model fails.",
     coverage_figure, False),
    ("residuals", "Residual against time and covariates",
     "The signed distance of each reading to the fitted surface against time, temperature and "
     "each auxiliary channel, with the binned rms; a trend here is an effect the model lacks. "
     "Shaded: outlier spans.", residuals_figure, False),
    ("ladder", "Model ladder and candidates",
     "Left: the rms after adding, one by one, the effect that explains most; it should fall to "
     "the noise floor. Right: what each candidate effect would give on its own, one panel per "
     "residual: misalignment and lag leave no trace where every direction is free, so they are "
     "measured on a residual whose direction is tied to gravity (or the gyro), which has its "
     "own, higher level. Compare each bar with the black line of its own panel (the model "
     "without the effect on that residual); the percentage is that change.", ladder_figure, True),
)


def render_figures(data: FigureData) -> list[RenderedFigure]:
    """Every figure that ``data`` supports, as PNG."""
    out = []
    for name, title, caption, draw, needs_diagnosis in FIGURES:
        if needs_diagnosis and data.diagnosis is None:
            continue
        out.append(RenderedFigure(name, title, caption, _png(draw(data))))
    return out
