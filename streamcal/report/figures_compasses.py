"""The compasses of one log compared over time (``report --compass all``): a figure of the angles
between their calibrated fields and an HTML section with the per-compass and per-pair tables."""
from __future__ import annotations

import base64
from html import escape

import numpy as np
from matplotlib.figure import Figure

from ..diagnosis.compass_consistency import CURRENT
from .figure_common import RenderedFigure, png_bytes, stride_index

_STYLE = {"autopilot": "-", "streamcal": "--"}


def consistency_figure(pairs) -> RenderedFigure:
    """3-D and horizontal angle (degrees) between each pair's calibrated fields over log time,
    with the limits the pairs applied (those of the log's firmware) as lines; ``pairs`` are
    :class:`PairConsistency`."""
    limits = pairs[0].limits if pairs else CURRENT
    fig = Figure(figsize=(9.0, 5.6))
    ax3, axh = fig.subplots(2, 1, sharex=True)
    for k, p in enumerate(pairs):
        idx = stride_index(len(p.t))
        colour = f"C{k % 10}"
        label = f"{p.a}–{p.b} ({p.calibration})"
        ax3.plot(p.t[idx], p.angle_deg[idx], _STYLE.get(p.calibration, "-"), color=colour,
                 linewidth=0.8, label=label)
        axh.plot(p.t[idx], p.xy_angle_deg[idx], _STYLE.get(p.calibration, "-"), color=colour,
                 linewidth=0.8, label=label)
    ax3.axhline(limits.angle_deg, color="#d62728", linewidth=1.0, label="ArduPilot limit")
    axh.axhline(limits.xy_angle_deg, color="#d62728", linewidth=1.0)
    ax3.set_ylabel("3-D angle (deg)")
    axh.set_ylabel("horizontal angle (deg)")
    axh.set_xlabel("log time (s)")
    for ax in (ax3, axh):
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    ax3.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    plane = pairs[0].xy_plane if pairs else "horizontal"
    caption = ("Angle between the calibrated field vectors of each pair of compasses over time: "
               "3-D (top) and in the " + plane + " plane (bottom); solid: the autopilot's "
               "calibration in force, dashed: streamcal's fit. Red lines: " + limits.text + ".")
    return RenderedFigure("compass-consistency", "Do the compasses agree?", caption,
                          png_bytes(fig))


def _num(value, fmt: str = ".3g") -> str:
    return "–" if value is None or (isinstance(value, float) and not np.isfinite(value)) \
        else format(value, fmt)


def compasses_section(entries: list[dict], pairs, figure: RenderedFigure | None,
                      limits=CURRENT) -> str:
    """HTML: a table of the compasses (instance, device id, verdict, rms or error), a table of
    the pairs (SPEC §6 ``consistency`` entries), the ``limits`` applied (a
    :class:`~streamcal.diagnosis.compass_consistency.ConsistencyLimits`) and the figure."""
    rows = "".join(
        f"<tr><td>{e['instance']}</td><td>{escape(str(e.get('device_id') or '–'))}</td>"
        f"<td>{escape(e['diagnosis']['verdict']) if e.get('diagnosis') else 'no fit'}</td>"
        f"<td class=\"num\">{_num(e['diagnosis']['rms']) if e.get('diagnosis') else '–'}</td>"
        f"<td>{escape(e.get('error') or '')}</td></tr>" for e in entries)
    prow = "".join(
        f"<tr><td>{p['a']}–{p['b']}</td><td>{escape(p['calibration'])}</td>"
        + "".join(f"<td class=\"num\">{_num(p[k])}</td>" for k in
                  ("angle_deg_median", "angle_deg_p95", "xy_angle_deg_median",
                   "xy_angle_deg_p95", "fraction_inconsistent")) + "</tr>"
        for p in (q.to_dict() for q in pairs))
    img = ""
    if figure is not None:
        data = base64.b64encode(figure.png).decode("ascii")
        img = (f'<figure id="fig-{figure.name}"><h3>{escape(figure.title)}</h3>'
               f'<img src="data:image/png;base64,{data}" alt="{escape(figure.title)}">'
               f"<figcaption>{escape(figure.caption)}</figcaption></figure>")
    return ('<section id="compasses"><h2>Every compass</h2>'
            "<table><thead><tr><th>compass</th><th>device id</th><th>verdict</th>"
            f"<th>rms (µT)</th><th>error</th></tr></thead><tbody>{rows}</tbody></table>"
            "<table><thead><tr><th>pair</th><th>calibration</th><th>angle median (°)</th>"
            "<th>angle p95 (°)</th><th>horizontal angle median (°)</th>"
            "<th>horizontal angle p95 (°)</th><th>share inconsistent</th></tr></thead>"
            f"<tbody>{prow}</tbody></table><p>{escape(limits.text)}.</p>{img}</section>")
