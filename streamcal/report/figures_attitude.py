"""The attitude reference as a picture: expected (World Magnetic Model rotated by the logged
attitude) and measured body-frame field per axis over time, before and after, and the heading
error each implies (:mod:`streamcal.fitting.attitude_reference`)."""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..fitting.attitude_reference import calibration_in_force, reference_series
from .figure_common import AFTER, FIT, INLIER, RenderedFigure, png_bytes, stride_index


def attitude_reference_figure(track, cal_before="in force", ref: dict | None = None,
                              channels=()) -> RenderedFigure | None:
    """Four panels (x, y, z in µT; heading error in degrees) over time; None when the track
    has no attitude or no position. ``cal_before``: a calibration, None for the readings as
    logged, or ``"in force"`` for the autopilot's calibration in the log's parameters."""
    if isinstance(cal_before, str):
        cal_before = calibration_in_force(track)
    s = reference_series(track, cal_before, ref=ref, channels=channels)
    if s is None:
        return None
    idx = stride_index(len(s["t"]))
    t = s["t"][idx]
    fig = Figure(figsize=(9, 8))
    axes = fig.subplots(4, 1, sharex=True)
    for k, (ax, name) in enumerate(zip(axes, "xyz")):
        ax.plot(t, s["expected"][idx, k], color=FIT, lw=1.2, label="expected (WMM × attitude)")
        ax.plot(t, s["before"][idx, k], color=INLIER, lw=0.7, alpha=0.8,
                label=f"measured, {s['before_label']}")
        ax.plot(t, s["after"][idx, k], color=AFTER, lw=0.7, alpha=0.8,
                label="measured, fitted against the reference")
        ax.set_ylabel(f"B{name} body (µT)")
    axes[0].legend(loc="upper right", fontsize=7)
    axes[3].plot(t, s["heading_before"][idx], color=INLIER, lw=0.7, label=s["before_label"])
    axes[3].plot(t, s["heading_after"][idx], color=AFTER, lw=0.7, label="fitted")
    axes[3].axhline(0.0, color=FIT, lw=0.5)
    axes[3].set_ylabel("heading error (°)")
    axes[3].set_xlabel("time (s)")
    axes[3].legend(loc="upper right", fontsize=7)
    rms = lambda v: float(np.sqrt(np.mean(v[s["inliers"]] ** 2)))  # noqa: E731
    fig.suptitle(f"attitude reference: heading error rms {rms(s['heading_before']):.2f}° "
                 f"({s['before_label']}) → {rms(s['heading_after']):.2f}° (fitted)")
    fig.tight_layout()
    return RenderedFigure(
        name="attitude_reference", title="Expected vs measured field (attitude reference)",
        caption="The World Magnetic Model field rotated into the body frame by the logged "
                "attitude, beside the measured field with the calibration in force and with the "
                "fit against it; bottom: the heading error each implies. The logged yaw itself "
                "uses the compass, so the error is a lower bound.",
        png=png_bytes(fig))
