"""The sphere figures: the raw readings around the fitted ellipsoid (``ellipsoid``) and the
coverage of the sphere of field directions on two Lambert equal-area discs (``coverage``)."""
from __future__ import annotations

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from ..sphere_cells import SphereCells, hint, largest_empty_cap
from .figure_common import FIT, INLIER, OUTLIER, stride_index, thin_index
from .figure_data import FigureData, unit_label

#: Equal-area cells of the coverage map (same partition as the streaming coverage buffer).
COVERAGE_CELLS = 300
_AXES = ("x", "y", "z")


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
    inl, out = thin_index(data.inliers), thin_index(~data.inliers)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        for line in lines:
            ax.plot(line[:, i], line[:, j], color=FIT, lw=0.6, alpha=0.55)
        ax.scatter(data.m[inl, i], data.m[inl, j], s=2, color=INLIER, alpha=0.35, lw=0,
                   rasterized=True, label=(f"inliers ({int(data.inliers.sum())})" if cal is not None
                                           else f"readings ({len(data.m)})"))
        if len(out):
            ax.scatter(data.m[out, i], data.m[out, j], s=10, color=OUTLIER, marker="x", lw=0.8,
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
    thin = data.directions[ok][stride_index(int(ok.sum()), 4000)]
    center, radius = largest_empty_cap(thin)
    return cells, count, rms, float((count > 0).mean()), center, radius


def coverage_figure(data: FigureData) -> Figure:
    import matplotlib
    from matplotlib import cm, colors

    cells, count, rms, fraction, gap_c, gap_r = coverage_cells(data)
    fig = Figure(figsize=(12, 5.4))
    axes = fig.subplots(1, 2)
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
                face.append(INLIER)
            elif np.isfinite(rms[c]):
                face.append(cmap(norm(rms[c])))
            else:
                face.append(OUTLIER)           # seen only in outliers
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
    title = (f"coverage of the sphere of field directions: {100 * fraction:.0f}% "
             f"({seen}/{cells.n_cells} equal-area cells; grey = never seen)\n" + second)
    fig.suptitle(title, fontsize=10)
    # room for every line of the title above the two subplot titles (≈ 0.19 in a line)
    lines = title.count("\n") + 1
    fig.subplots_adjust(left=0.02, right=0.86, bottom=0.02, wspace=0.05,
                        top=1.0 - (0.19 * lines + 0.42) / fig.get_figheight())
    return fig


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))
