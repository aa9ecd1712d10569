"""What every figure shares: the colours, thinning of large tracks for scatter plots, the PNG
encoding without software/date metadata (same inputs, same bytes) and :class:`RenderedFigure`."""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .figure_data import FigureData

#: Most points drawn per scatter series (a fixed stride thins the rest).
MAX_POINTS = 5000
DPI = 100
_PNG_METADATA = {"Software": None}
INLIER, OUTLIER, FIT, AFTER = "#1f5fa8", "#d62728", "#444444", "#2ca02c"
SPAN = "#f4b6b6"


@dataclass(frozen=True)
class RenderedFigure:
    """One figure: ``name`` (file stem), ``title``, ``caption`` (what it shows) and ``png``
    bytes."""

    name: str
    title: str
    caption: str
    png: bytes


def stride_index(n: int, limit: int = MAX_POINTS) -> np.ndarray:
    """At most ``limit`` indices into ``n`` samples, a fixed stride (all of them when fewer)."""
    return np.arange(n) if n <= limit else np.unique(np.linspace(0, n - 1, limit).astype(int))


def thin_index(mask: np.ndarray, limit: int = MAX_POINTS) -> np.ndarray:
    """At most ``limit`` indices of the true entries of ``mask`` (N,), a fixed stride."""
    idx = np.flatnonzero(mask)
    return idx[stride_index(len(idx), limit)]


def png_bytes(fig: Figure) -> bytes:
    """``fig`` as PNG at :data:`DPI`, without software/date metadata."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata=_PNG_METADATA)
    return buf.getvalue()


def note(ax, text: str) -> None:
    """``text`` in the middle of an empty ``ax``."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=10,
            color="#555555", wrap=True)
    ax.set_xticks([])
    ax.set_yticks([])


def shade_spans(ax, data: FigureData) -> None:
    """Shade the diagnosis' outlier spans on a time axis."""
    spans = data.diagnosis.outlier_spans if data.diagnosis is not None else []
    for k, (a, b) in enumerate(spans):
        ax.axvspan(a, b, color=SPAN, alpha=0.6, lw=0, label="outlier span" if k == 0 else None)
