"""The model ladder and the candidates, each rms against the model without the effect on the
same residual (``ladder``), and the helpers the page's tables share with it."""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..diagnosis.diagnosis import RESIDUAL_LABELS
from ..diagnosis.story import change_percent
from .figure_common import AFTER, INLIER, OUTLIER, note
from .figure_data import FigureData, unit_label


#: The residual families an rms of the diagnosis can be on (``Diagnosis.residual``,
#: ``candidate_baselines``, ladder ``residual``): (label, what it is, colour, noise alone as a
#: multiple of the noise floor). The floor is the noise along one axis, which the sensor
#: residual keeps (eq. 41: the free direction absorbs the two tangent components); with the
#: direction tied to gravity only the heading is free, so two components stay (√2 × floor) and
#: the gravity reference's own error adds to that; the gyro-tied residual compares two samples,
#: two components each (≈ 2 × floor, :mod:`streamcal.fitting.gyro_lag`).
RESIDUAL_FAMILIES = {
    "sensor": (f"{RESIDUAL_LABELS['sensor']} residual", "the reading's distance to the fitted surface",
               INLIER, 1.0),
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


def relative_change(before: float, after: float, digits: int = 4) -> str:
    """Relative change ``after / before − 1`` as text ("−39 %", "±0 %") of the two numbers as
    shown with ``digits`` significant digits."""
    pct = change_percent(before, after, digits)
    if pct is None:
        return ""
    pct = round(pct)
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
        ax.annotate(relative_change(before, step["rms"], 3), ((k - 0.5), (before + step["rms"]) / 2),
                    xytext=(4, 4), textcoords="offset points", ha="left", va="bottom", fontsize=9,
                    color=colour, fontweight="bold")
    families = list(dict.fromkeys(s["residual"] for s in steps))
    if np.isfinite(floor):
        for fam in families:
            label, _, colour, factor = RESIDUAL_FAMILIES[fam]
            level = factor * floor
            ax.axhline(level, color=AFTER if fam == "sensor" else colour,
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
    ax.barh(y, after, color=[AFTER if c.significant else "#bbbbbb" for c in cands],
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
        ax.axvline(level, color=AFTER if residual == "sensor" else colour,
                   ls="--" if residual == "sensor" else ":", lw=1.5)
        values.append(level)
    finite = np.asarray(values, float)[np.isfinite(values)]
    xmax = 1.32 * finite.max() if finite.size and finite.max() > 0 else 1.0
    if np.isfinite(d.noise_floor):   # text left of the line, or right of it near the axis
        left = level > 0.25 * xmax
        ax.text(level, 0.02, (_FLOOR_TEXT[residual] + " ") if left else
                (" " + _FLOOR_TEXT[residual]), transform=top, ha="right" if left else "left",
                va="bottom", fontsize=7, color=AFTER if residual == "sensor" else colour)
    ax.set_xlim(0, xmax)
    right = ax.get_yaxis_transform()
    for yi, c, a in zip(y, cands, after):
        own = d.baseline(c)[1]   # on the samples the model with this candidate keeps
        worse = a > own * 1.005
        ax.text(0.995, yi, f"{own:.3g} → {a:.3g}  {relative_change(own, a, 3)}", transform=right,
                ha="right",
                va="center", fontsize=8, color=OUTLIER if worse else
                (AFTER if c.significant else "#555555"),
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
        note(ax, "no candidate effect can be tried on this track")
        ax.set_title("candidate effects, best first", fontsize=10, pad=16)
    for i, (residual, before, cands) in enumerate(groups):
        _candidate_panel(fig.add_subplot(gs[i, 1]), d, residual, before, cands, unit, i == 0)
    fig.tight_layout()
    return fig
