"""The residual before and after the top effect is added, against time and against motor
output, current, throttle and temperature — the figure a drone user wants.

One panel against time (``t``, always: drift, warm-up and whatever else is slow), then for each auxiliary channel the recording carries (the ones the residual follows most first,
from the diagnosis' ``aux_channels`` scores, at most :data:`MAX_PANELS`) and for ``temp``, one
panel: the signed sensor residual (eq. 41: distance of each reading from the model surface along
its normal, in the sensor unit) binned by the channel into :data:`N_BINS` equal-count bins, the
median of each bin as a line and its 25–75 % spread as a band — for the model as diagnosed and
for the model with the top candidate added, on the same axes. A motor field shows as a slope of
the "before" curve that the "after" curve does not have. Every sample counts (outliers too: the
segments a motor field moves are where it shows).
"""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..diagnosis.held.fit import project
from ..model import TERMS, terms_from_params
from .figure_common import RenderedFigure, png_bytes
from .figure_data import unit_label

MAX_PANELS = 4
N_BINS = 16
#: Units of the channels the readers produce (by name, else by suffix).
CHANNEL_UNITS = {"t": "s", "throttle": "0..1", "temp": "°C", "motor_current": "A"}
SUFFIX_UNITS = (("_a", "A"), ("_v", "V"), ("_c", "°C"))
_BEFORE, _AFTER = "#1f5fa8", "#2ca02c"
NAME = "aux_residuals"
TITLE = "Residual before and after the top effect, against time and each channel"


def channel_unit(name: str) -> str:
    """Display unit of a covariate column named by the readers (``rcou_c1`` → µs)."""
    if name in CHANNEL_UNITS:
        return CHANNEL_UNITS[name]
    if name.startswith(("rcou_", "act_out")):
        return "µs" if name.startswith("rcou_") else "actuator output"
    for suffix, unit in SUFFIX_UNITS:
        if name.endswith(suffix):
            return unit
    return "as logged"


def signed_residual(cal, m: np.ndarray, cov) -> np.ndarray:
    """(N,) signed normal residual of calibration ``cal`` on readings ``m`` (sensor unit)."""
    terms = [(t, th) for t, th in terms_from_params(cal.effects or {}) if t.name in TERMS]
    return project(cal.K, cal.b, terms, np.asarray(m, float), cov)[2]


def _scores(diagnosis) -> dict:
    """``{channel: r}`` of a diagnosis against a held calibration; {} for a fresh one."""
    held = getattr(diagnosis, "held", None)
    return held.aux_channels if held is not None else {}


def _channels(diagnosis, cov) -> list[str]:
    scored = [c for c in _scores(diagnosis) if c in cov]
    rest = [c for c in cov if c not in scored and c not in (
        "t", "temp", "ax", "ay", "az", "gx", "gy", "gz")]
    chans = ["t"] + (scored + rest)[:MAX_PANELS]
    if "temp" in cov and np.ptp(np.asarray(cov["temp"], float)) > 0:
        chans.append("temp")
    return [c for c in chans if np.ptp(np.asarray(cov[c], float)) > 0]


def _binned(x: np.ndarray, y: np.ndarray):
    """Bin centres (median x), medians and 25/75 % quantiles of y over equal-count bins."""
    order = np.argsort(x, kind="stable")
    parts = [p for p in np.array_split(order, min(N_BINS, max(1, len(x) // 10))) if len(p)]
    xc = np.array([np.median(x[p]) for p in parts])
    q = np.array([np.percentile(y[p], [25, 50, 75]) for p in parts])
    return xc, q[:, 1], q[:, 0], q[:, 2]


def aux_residual_figure(track, diagnosis) -> RenderedFigure | None:
    """The figure, or None when the diagnosis has no calibration to compute a residual from."""
    cal = getattr(diagnosis, "calibration", None)
    if diagnosis is None or cal is None:
        return None
    cov = {k: np.asarray(v, float) for k, v in track.covariates_at_mag().items()}
    cov.setdefault("t", np.asarray(track.t_mag, float))
    chans = _channels(diagnosis, cov)
    if not chans:
        return None
    m = np.asarray(track.mag, float)
    unit = unit_label(track.mag_unit)
    before = signed_residual(cal, m, cov)
    top = diagnosis.candidates[0] if diagnosis.candidates else None
    after, added = None, ""
    if top is not None and top.calibration is not None and \
            getattr(top, "residual", "sensor") == "sensor":
        after, added = signed_residual(top.calibration, m, cov), top.effect
    fig = Figure(figsize=(4.2 * len(chans), 3.8))
    axes = fig.subplots(1, len(chans), squeeze=False)[0]
    for ax, ch in zip(axes, chans):
        x = cov[ch]
        ok = np.isfinite(x) & np.isfinite(before)
        for y, colour, label in ((before, _BEFORE, "model as diagnosed"),
                                 (after, _AFTER, f"with {added}")):
            if y is None:
                continue
            xc, med, lo, hi = _binned(x[ok], y[ok])
            ax.fill_between(xc, lo, hi, color=colour, alpha=0.2, linewidth=0)
            ax.plot(xc, med, "-o", color=colour, markersize=3, label=f"{label} (median, 25–75 %)")
        ax.axhline(0.0, color="#888888", linewidth=0.8)
        score = _scores(diagnosis).get(ch)
        ax.set_title(ch + (f"  (r = {score:.2f})" if score is not None else ""), fontsize=10)
        ax.set_xlabel(f"{ch} ({channel_unit(ch)})")
        ax.set_ylabel(f"signed sensor residual ({unit})")
    axes[0].legend(fontsize=8, loc="best")
    fig.tight_layout()
    caption = (f"The signed sensor residual (distance of each of the {len(m)} readings from the "
               f"model surface along its normal, {unit}) in {N_BINS} equal-count bins of each "
               "channel: median line, 25–75 % band. Blue: the model as diagnosed"
               + (f"; green: with the top candidate, {added}, added" if added else "")
               + ("" if added or top is None else f"; the top candidate, {top.effect}, is judged on "
                  f"the {top.residual.replace('_', '-')} residual, so it is not drawn on this "
                  "one (the ladder figure compares it)")
               + ". A field that follows the channel shows as a slope of the blue curve; r is "
               "how closely the residual follows that channel alone.")
    return RenderedFigure(NAME, TITLE, caption, png_bytes(fig))
