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


@pytest.mark.slow
def test_before_after_figure_of_the_top_effect_exists_without_aux_channels(tmp_path):
    """A track with no motor/current column still gets the residual before and after its top
    effect, against time, on the same axes."""
    from streamcal.report.figures_aux import aux_residual_figure
    from streamcal.sim import simulate

    sim = simulate(120.0, seed=4, effects={"time_drift": 0.05}, motor=False).track
    track = Track({k: v for k, v in sim.columns.items() if k != "temp"}, sim.metadata)
    assert not track.aux_names and not track.has("temp")
    d = diagnose(track)
    assert d.candidates and d.candidates[0].effect == "time_drift"
    fig = aux_residual_figure(track, d)
    assert fig is not None and "with the top candidate, time_drift, added" in fig.caption
    assert fig.png.startswith(b"\x89PNG")
