"""The report: figures render headless and deterministically, the HTML page is self-contained
and says what the diagnosis found (or why there is none), ``diagnose --plots`` writes the PNGs,
and the terminal coverage view shows the sphere as the coverage buffer sees it."""
import base64
import html
import io
import re

import numpy as np
import pytest
from matplotlib.image import imread
from matplotlib.path import Path as MplPath

from streamcal.cli import main
from streamcal.diagnosis import diagnose
from streamcal.report import (FigureData, coverage_map, coverage_view, render_figures,
                              render_html, write_diagnosis_plots, write_report)
from streamcal.report.figures import FIGURES
from streamcal.report.figures_sphere import cell_polygons, lambert
from streamcal.report.terminal import EMPTY, FILLED
from streamcal.sim import simulate
from streamcal.stream import CoverageBuffer
from streamcal.sphere_cells import SphereCells, fibonacci_sphere

HIDDEN = "temperature_offset"
TRIED = [HIDDEN, "time_drift", "aux_interference"]
ALL_FIGURES = [f[0] for f in FIGURES]


@pytest.fixture(scope="module")
def hidden():
    track = simulate(40.0, 11, effects={HIDDEN: 0.6}, outlier_bursts=1).track
    return track, diagnose(track, candidates=TRIED)


@pytest.fixture(scope="module")
def clean():
    track = simulate(40.0, 12).track
    return track, diagnose(track, candidates=TRIED)


def _images(page: str) -> list[bytes]:
    srcs = re.findall(r'<img[^>]*\ssrc="([^"]*)"', page)
    assert len(srcs) == len(re.findall(r"<img\s", page))
    out = []
    for src in srcs:
        assert src.startswith("data:image/png;base64,"), src[:60]
        out.append(base64.b64decode(src.split(",", 1)[1], validate=True))
    return out


def _assert_not_blank(png: bytes) -> None:
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    pixels = imread(io.BytesIO(png), format="png")
    assert pixels.shape[0] > 100 and pixels.shape[1] > 100
    rgb = pixels[..., :3]
    assert rgb.std() > 0.02                       # not one flat colour
    assert (rgb.mean(axis=2) < 0.5).mean() > 0.002  # some dark ink (axes, text, points)


def _assert_self_contained(page: str) -> None:
    lower = page.lower()
    for needle in ("http://", "https://", "<link", "@import", "url(", " href="):
        assert needle not in lower, needle


@pytest.mark.slow
def test_hidden_effect_report_names_the_effect_and_inlines_every_figure(hidden):
    track, d = hidden
    assert d.verdict == "effect_missing" and d.candidates[0].effect == HIDDEN
    page = render_html(track, d)
    _assert_self_contained(page)
    images = _images(page)
    # plus the residual against the aux channels / temperature (report/figures_aux.py)
    assert len(images) == len(ALL_FIGURES) + 1
    for name in (*ALL_FIGURES, "aux_residuals"):
        assert f'id="fig-{name}"' in page
    for png in images:
        _assert_not_blank(png)
    summary = page.split('class="box missing"', 1)[1].split("</div>", 1)[0]
    assert HIDDEN in summary and f"--add {HIDDEN}" in summary
    for c in d.candidates:                       # every candidate in the table
        assert f"<td>{c.effect}</td>" in page
    assert "µT/°C" in page                       # the added effect's parameters with units
    assert f"{d.noise_floor:.4g}" in page


def test_residual_figure_has_a_panel_per_covariate(hidden):
    track, d = hidden
    data = FigureData.build(track, d)
    fig = dict((f[0], f[3]) for f in FIGURES)["residuals"](data)
    labels = [ax.get_xlabel() for ax in fig.axes]
    assert labels[0] == "time (s)" and "temperature (°C)" in labels
    assert any("motor_current" in label for label in labels)
    # the outlier burst is shaded on the time axis
    assert d.outlier_spans and len(fig.axes[0].patches) >= len(d.outlier_spans)


@pytest.mark.slow
def test_clean_report_says_at_noise_floor(clean):
    track, d = clean
    assert d.verdict == "at_noise_floor"
    page = render_html(track, d)
    assert 'class="box floor"' in page and 'class="box missing"' not in page
    for png in _images(page):
        _assert_not_blank(png)


@pytest.mark.slow
def test_renders_are_byte_identical(hidden, tmp_path):
    track, d = hidden
    assert render_html(track, d) == render_html(track, d)
    a = write_diagnosis_plots(d, track, tmp_path / "a")
    b = write_diagnosis_plots(d, track, tmp_path / "b")
    assert [p.name for p in a] == [f"{n}.png" for n in ALL_FIGURES]
    for pa, pb in zip(a, b):
        assert pa.read_bytes() == pb.read_bytes()


def test_refused_track_still_renders_what_it_can(tmp_path):
    track = simulate(30.0, 5, coverage="hemisphere").track
    reason = "the directions seen cover 48% of the sphere: turn the board over"
    out = write_report(tmp_path / "r.html", track, None, reason=reason)
    page = out.read_text()
    assert 'class="box refused"' in page and reason in page
    names = re.findall(r'id="fig-(\w+)"', page)
    assert names == [n for n in ALL_FIGURES if n != "ladder"]
    for png in _images(page):
        _assert_not_blank(png)


@pytest.mark.slow
def test_diagnose_plots_writes_the_pngs(tmp_path, capsys):
    path = tmp_path / "t.csv.gz"
    simulate(30.0, 7, effects={"time_drift": 0.06}).track.write(path)
    assert main(["diagnose", str(path), "--plots", str(tmp_path / "plots")]) == 0
    written = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert written == sorted(f"{n}.png" for n in ALL_FIGURES)
    for p in (tmp_path / "plots").iterdir():
        _assert_not_blank(p.read_bytes())


@pytest.mark.slow
def test_report_cli_with_added_effect(tmp_path, capsys):
    path = tmp_path / "t.csv.gz"
    simulate(30.0, 8, effects={HIDDEN: 0.6}).track.write(path)
    out = tmp_path / "x.html"
    assert main(["report", str(path), "--add", HIDDEN, "-o", str(out)]) == 0
    page = out.read_text()
    assert f"<code>hard_iron, soft_iron, {HIDDEN}</code>" in page or "box floor" in page
    assert f"<td>{HIDDEN}: c</td>" in page      # the effect's parameters are in the table
    assert str(out) in capsys.readouterr().out


def test_report_cli_unknown_effect_is_a_usage_error(tmp_path, capsys):
    path = tmp_path / "t.csv"
    simulate(10.0, 9).track.write(path)
    assert main(["report", str(path), "--add", "no_such_effect", "-o", str(tmp_path / "r.html")]) == 2
    assert not (tmp_path / "r.html").exists()
    assert "no_such_effect" in capsys.readouterr().err


@pytest.mark.slow
def test_broad_32_is_refused_and_the_report_says_why(real_tracks_dir, tmp_path, capsys):
    src = real_tracks_dir / "broad_32_attached_magnet_1cm.csv.gz"
    out = tmp_path / "broad32.html"
    code = main(["report", str(src), "-o", str(out)])
    page = out.read_text()
    for png in _images(page):
        _assert_not_blank(png)
    _assert_self_contained(page)
    if code == 1:                                # the fit refused the track: the page says why
        err = capsys.readouterr().err
        reason = err.split("no calibration: ", 1)[1].split(" (the report", 1)[0]
        assert 'class="box refused"' in page and reason in html.unescape(page)
    else:
        assert code == 0 and ('class="box missing"' in page or 'class="box floor"' in page)


# -- geometry of the coverage map ----------------------------------------------------------
def _area(poly):
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@pytest.mark.parametrize("north", [True, False])
def test_coverage_cells_are_equal_area_and_hold_their_samples(north):
    cells = SphereCells(300)
    polys, ids = cell_polygons(cells, north, n_arc=64)
    assert len(ids) == cells.n_cells // 2
    areas = np.array([_area(p) for p in polys])
    # Lambert azimuthal equal-area: every cell keeps its area 4π/C on the plane
    np.testing.assert_allclose(areas, 4 * np.pi / cells.n_cells, rtol=0.01)
    d = fibonacci_sphere(4000)
    d = d[(d[:, 2] > 0) == north]
    xy, cell = lambert(d, north), cells.cell_of(d)
    for poly, c in zip(polys, ids):
        mine = cell == c
        inside = MplPath(poly).contains_points(xy[mine], radius=1e-9)
        assert inside.mean() > 0.95


# -- terminal view ------------------------------------------------------------------------
def _buffer(directions):
    buf = CoverageBuffer(n_cells=300)
    buf.insert(40.0 * directions + np.array([5.0, -3.0, 2.0]), np.arange(len(directions)) * 0.01)
    buf.set_frame([5.0, -3.0, 2.0], np.eye(3) / 40.0)
    return buf


def _discs(text):
    rows = [line for line in text.splitlines() if FILLED in line or EMPTY in line]
    rows = [line for line in rows if not line.startswith(("█ seen", "coverage", "hint"))]
    mid = max(len(r) for r in rows) // 2
    return "".join(r[:mid] for r in rows), "".join(r[mid:] for r in rows)


def test_terminal_view_full_sphere_is_all_filled():
    buf = _buffer(fibonacci_sphere(6000))
    text = coverage_view(buf)
    assert f"coverage {100 * buf.fraction:.0f}%" in text and buf.fraction > 0.99
    north, south = _discs(text)
    assert north.count(FILLED) > 50 and south.count(FILLED) > 50
    empty_cells = buf.cells.n_cells - int(buf.occupied.sum())
    assert (north + south).count(EMPTY) <= 3 * empty_cells   # a cell spans a few characters
    assert "hint: coverage is good" in text
    every = coverage_map(buf.cells, np.ones(buf.cells.n_cells, bool))
    assert EMPTY not in every and every.count(FILLED) > 100


def test_terminal_view_shows_the_missing_hemisphere():
    d = fibonacci_sphere(6000)
    buf = _buffer(d[d[:, 2] > 0])
    report = buf.report()
    text = coverage_view(buf, report)
    north, south = _discs(text)
    assert north.count(FILLED) > 0.9 * (north.count(FILLED) + north.count(EMPTY))
    assert south.count(EMPTY) > 0.9 * (south.count(FILLED) + south.count(EMPTY))
    assert "○" in south and "○" not in north       # the gap's centre is marked under the board
    assert "underside (−Z)" in text and report.hint.split()[0] in text


def test_terminal_map_ascii_and_empty():
    cells = SphereCells(300)
    text = coverage_map(cells, np.zeros(cells.n_cells, bool), rows=5, ascii=True)
    assert text.isascii() and "#" not in text and "." in text
    lines = text.splitlines()
    assert len(lines) == 5 + 3
