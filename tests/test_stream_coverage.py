"""CoverageBuffer: equal-area cells, coverage figures on known direction sets, bounded memory."""
import numpy as np
import pytest

from streamcal.stream.coverage import CoverageBuffer
from streamcal.sphere_cells import (SphereCells, describe_direction, fibonacci_sphere,
                                           largest_empty_cap)


@pytest.mark.parametrize("n_cells", [100, 300, 500])
def test_cells_are_equal_area_and_cover_the_sphere(n_cells):
    cells = SphereCells(n_cells)
    assert 0.8 * n_cells <= cells.n_cells <= 1.2 * n_cells
    # Uniform points fall evenly into equal-area cells.
    d = fibonacci_sphere(200 * cells.n_cells)
    counts = np.bincount(cells.cell_of(d), minlength=cells.n_cells)
    assert counts.min() > 0.9 * 200 and counts.max() < 1.1 * 200
    # Each centre lies in its own cell.
    np.testing.assert_array_equal(cells.cell_of(cells.centers), np.arange(cells.n_cells))


def test_full_sphere_is_fully_covered():
    buf = CoverageBuffer(n_cells=300)
    d = fibonacci_sphere(5000)
    buf.insert(d * 50.0, np.arange(len(d), dtype=float))
    report = buf.report()
    assert report.fraction == pytest.approx(1.0)
    assert report.empty_cap_deg < 10.0
    assert "no action" in report.hint


@pytest.mark.parametrize("pole", [+1, -1])
def test_hemisphere(pole):
    buf = CoverageBuffer(n_cells=300)
    d = fibonacci_sphere(5000)
    d = d[pole * d[:, 2] >= 0]
    buf.insert(d, np.arange(len(d), dtype=float))
    report = buf.report()
    assert report.fraction == pytest.approx(0.5, abs=0.03)
    assert report.empty_cap_deg == pytest.approx(90.0, abs=3.0)
    assert report.empty_cap_center @ [0, 0, -pole] > np.cos(np.radians(5))
    assert ("underside (−Z)" if pole > 0 else "top (+Z)") in report.hint


def test_equatorial_band():
    buf = CoverageBuffer(n_cells=300)
    d = fibonacci_sphere(5000)
    d = d[np.abs(d[:, 2]) <= np.sin(np.radians(20))]
    buf.insert(d, np.arange(len(d), dtype=float))
    report = buf.report()
    band = np.sin(np.radians(20))          # area fraction of a ±20° band
    # Cells cut by the band edges count as covered: at most one band row of cells on each side.
    assert band <= report.fraction <= band + 2 * 31 / buf.cells.n_cells
    assert report.empty_cap_deg == pytest.approx(70.0, abs=3.0)
    assert abs(report.empty_cap_center[2]) > np.cos(np.radians(5))


def test_memory_is_fixed_and_spacing_kept():
    buf = CoverageBuffer(n_cells=200, slots=3, min_spacing_deg=6.3)
    before = buf.nbytes
    rng = np.random.default_rng(0)
    for k in range(50):
        m = rng.normal(size=(2000, 3))
        buf.insert(m, k * 2000 + np.arange(2000.0))
    assert buf.nbytes == before
    assert buf.n_samples <= buf.capacity
    d = buf.stored_directions()
    cells = buf.cells.cell_of(d)
    for c in np.unique(cells):                      # stored samples of a cell are spaced apart
        dc = d[cells == c]
        cos = dc @ dc.T - 2 * np.eye(len(dc))
        assert cos.max() <= np.cos(np.radians(6.3)) + 1e-12


def test_newest_samples_are_kept():
    buf = CoverageBuffer(n_cells=100, slots=2)
    d = fibonacci_sphere(3000)
    buf.insert(d, np.arange(3000.0))
    buf.insert(d, 10_000 + np.arange(3000.0))       # the same directions, later
    snap = buf.snapshot()
    assert snap.t.min() >= 10_000
    assert np.all(np.diff(snap.t) >= 0)             # oldest first


def test_reframe_rebins_and_forget():
    buf = CoverageBuffer(n_cells=300)
    d = fibonacci_sphere(3000)
    d = d[d[:, 2] >= 0]
    m = np.array([0.0, 0.0, 20.0]) + 50.0 * d       # offset: raw directions are skewed
    buf.insert(m, np.arange(len(m), dtype=float))
    raw = buf.fraction
    buf.set_frame(center=[0.0, 0.0, 20.0], A=np.eye(3) / 50.0)
    assert buf.fraction == pytest.approx(0.5, abs=0.03)
    assert raw < 0.45                               # the frame mattered
    assert buf.report().empty_cap_deg == pytest.approx(90.0, abs=3.0)
    n = buf.n_samples
    t_cut = np.median(buf.snapshot().t)
    dropped = buf.forget_before(t_cut)
    assert dropped > 0 and buf.n_samples == n - dropped
    assert buf.snapshot().t.min() >= t_cut


def test_covariates_travel_with_samples():
    buf = CoverageBuffer(n_cells=100, covariates=("temp", "current"))
    d = fibonacci_sphere(500)
    t = np.arange(500.0)
    buf.insert(d, t, {"temp": 20 + t / 100, "current": None})
    snap = buf.snapshot()
    np.testing.assert_allclose(snap.covariates["temp"], 20 + snap.t / 100)
    assert np.isnan(snap.covariates["current"]).all()


def test_largest_empty_cap_single_point_and_empty():
    center, radius = largest_empty_cap(np.array([[0.0, 0.0, 1.0]]))
    assert radius == pytest.approx(180.0, abs=3.0) and center[2] < -0.99
    assert largest_empty_cap(np.zeros((0, 3)))[1] == 180.0


def test_describe_direction():
    assert describe_direction([0, 0, -1]) == "the underside (−Z)"
    assert describe_direction([0.7, 0, -0.7]) in ("the nose (+X) and the underside (−Z)",
                                                  "the underside (−Z) and the nose (+X)")
