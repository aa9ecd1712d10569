"""Figure layout: titles never run into each other (a long coverage hint wraps onto several
lines above the two sphere maps)."""
from __future__ import annotations

import pytest

from streamcal.diagnosis import diagnose
from streamcal.inputs.track import Track
from streamcal.report.figure_data import FigureData
from streamcal.report.figures_sphere import coverage_figure


@pytest.mark.slow
def test_coverage_title_clears_the_subplot_titles(real_tracks_dir):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    track = Track.read(real_tracks_dir / "broad_30_stationary_magnet_C.csv.gz")
    fig = coverage_figure(FigureData.build(track, diagnose(track)))
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    title = fig._suptitle
    assert title.get_text().count("\n") >= 2          # the case that used to overlap: a long hint
    top = title.get_window_extent(renderer)
    for ax in fig.axes:
        if ax.get_title():
            box = ax.title.get_window_extent(renderer)
            assert box.y1 < top.y0, (ax.get_title(), box, top)
