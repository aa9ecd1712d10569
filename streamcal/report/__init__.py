"""Pictures of a diagnosis (DESIGN §2 ``streamcal/report``): figures as PNG, one self-contained
HTML page, and a compact terminal view of sphere coverage.

    from streamcal.report import write_report, write_diagnosis_plots, coverage_view
    d = streamcal.diagnose(track)
    write_report("report.html", track, d)          # or d=None, reason="why the fit refused"
    write_diagnosis_plots(d, track, "plots/")      # the same figures as PNG files
    print(coverage_view(calibrator.buffer))        # terminal map of the sphere
"""
from __future__ import annotations

import os
from pathlib import Path

import importlib

from .terminal import coverage_map, coverage_view

# The figures and the page load matplotlib: imported on first use, so that the terminal view
# (drawn by the services at coverage milestones) does not load it (startup, issue #12).
_LAZY = {"FigureData": "figure_data", "RenderedFigure": "figure_common",
         "render_figures": "figures", "render_html": "html", "write_report": "html"}


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["FigureData", "RenderedFigure", "coverage_map", "coverage_view", "diagnose_or_reason",
           "render_figures", "render_html", "write_diagnosis_plots", "write_report"]


def write_diagnosis_plots(diagnosis, track, directory: str | os.PathLike,
                          reason: str | None = None) -> list[Path]:
    """Write every figure of ``diagnosis`` (None: the raw-data figures, ``reason`` saying why)
    on ``track`` as ``DIRECTORY/<name>.png`` (atomically; the directory is created). Returns the
    paths written."""
    from ..atomic import atomic_write_bytes, output_dir
    from .figure_data import FigureData
    from .figures import render_figures

    directory = output_dir(directory)
    paths = []
    for fig in render_figures(FigureData.build(track, diagnosis, reason)):
        path = directory / f"{fig.name}.png"
        atomic_write_bytes(path, fig.png, mode=0o644)
        paths.append(path)
    return paths


def diagnose_or_reason(track, model=None, **kwargs):
    """``(diagnosis, None)``, or ``(None, reason)`` when the data cannot support a fit
    (:class:`~streamcal.errors.InsufficientDataError`: too little coverage, too few samples).
    Other errors (bad input, unknown effect) propagate."""
    from ..calibration import DEFAULT_MODEL
    from ..diagnosis import diagnose
    from ..errors import InsufficientDataError

    try:
        return diagnose(track, model=tuple(model or DEFAULT_MODEL), **kwargs), None
    except InsufficientDataError as exc:
        return None, str(exc)
