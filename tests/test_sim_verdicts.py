"""Verdicts, residual names and report text on simulated recordings: what tests/test_verdicts.py,
tests/test_human_output.py, tests/test_report.py, tests/test_report_layout.py and
tests/test_diagnose_against.py check on real tracks.

The real cases and their simulated stand-ins: a residual several times a measurable floor that no
candidate explains (tiva 01/06) — an axis nonlinearity diagnosed with a catalog that lacks it; a
floor the recording cannot measure (jr_mpu9250 at 3.3 Hz, turned by hand) — the same rate
simulated; a significant but immaterial effect (tiva 01's time drift) — a small simulated drift;
a time lag of milliseconds (broad_30) — an 11 ms lag; a long coverage hint (broad_30) — a
hemisphere; a refused track (broad_32) — a planar turn; a cap of a short noisy recording
(tiva 03)."""
from __future__ import annotations

import html
import re

import pytest

from streamcal.cli import main
from streamcal.diagnosis import diagnose
from streamcal.fitting import fit
from streamcal.inputs.track import Track
from streamcal.sim import simulate

from ._shared_checks import (check_fit_json_names_the_residual,
                             check_held_verdict_follows_the_same_rules,
                             check_report_heading_names_the_file,
                             check_significance_and_materiality_apart,
                             check_tied_fit_names_both_residuals,
                             check_unexplained_above_a_measured_floor,
                             check_unmeasurable_floor_is_null_with_its_reason)
from .test_diagnose_against import check_cap_against_its_full_calibration
from .test_human_output import LONG_FLOAT
from .test_report import _assert_not_blank, _assert_self_contained, _images

#: An effect the restricted catalog below cannot express, so the residual stays unexplained.
UNLISTED = {"axis_nonlinearity": 1.0}
CATALOG_WITHOUT_IT = ["time_lag", "temperature_offset"]


@pytest.fixture(scope="module")
def unexplained():
    track = simulate(60.0, 31, effects=UNLISTED, motor=False).track
    return track, diagnose(track, candidates=CATALOG_WITHOUT_IT)


def test_rms_well_above_a_measured_floor_is_unexplained(unexplained):
    check_unexplained_above_a_measured_floor(*unexplained)


def test_against_a_calibration_the_verdict_follows_the_same_rules(unexplained):
    track, fresh = unexplained
    check_held_verdict_follows_the_same_rules(
        diagnose(track, calibration=fresh.calibration, candidates=CATALOG_WITHOUT_IT))


def test_a_floor_the_recording_cannot_measure_is_null_with_its_reason():
    """3.33 Hz turned by hand: the second differences measure the motion, not the noise."""
    track = simulate(120.0, 32, mag_rate_hz=3.33, imu_rate_hz=3.33, motor=False).track
    check_unmeasurable_floor_is_null_with_its_reason(track, diagnose(track))


def test_significance_and_materiality_are_reported_apart_with_their_rule():
    """A small drift: p far below 1e-6 (significant) but the rms falls by a few % (not
    material); the text shows both tests and the rule with its numbers."""
    check_significance_and_materiality_apart(
        diagnose(simulate(60.0, 33, effects={"time_drift": 0.01}, motor=False).track))


@pytest.fixture(scope="module")
def lagged(tmp_path_factory):
    path = tmp_path_factory.mktemp("lag") / "lagged.csv"
    simulate(60.0, 41, effects={"time_lag": 0.011}, motor=False).track.write(path)
    return path


def test_fit_of_a_tied_effect_names_both_residuals_and_the_lag_in_ms(lagged, capsys):
    assert main(["fit", str(lagged), "--add", "time_lag"]) == 0
    text = capsys.readouterr().out
    check_tied_fit_names_both_residuals(text)
    lag = re.search(r"time_lag: tau (-?[\d.]+) ms", text)
    assert lag, text
    assert 1.0 < abs(float(lag.group(1))) < 100.0        # milliseconds, not seconds
    assert not LONG_FLOAT.search(text) and "tau=" not in text


def test_fit_json_names_the_residual(tmp_path, capsys):
    path = tmp_path / "tilted.csv"
    simulate(40.0, 43, effects={"mag_accel_misalignment": 0.06}, motor=False).track.write(path)
    check_fit_json_names_the_residual(path, capsys)


def test_report_heading_names_the_file_not_its_folder(lagged, tmp_path):
    assert check_report_heading_names_the_file(lagged, tmp_path / "r.html") == 0


@pytest.fixture(scope="module")
def hemisphere(tmp_path_factory):
    path = tmp_path_factory.mktemp("hemi") / "hemisphere.csv.gz"
    simulate(30.0, 42, coverage="hemisphere", motor=False).track.write(path)
    return path


@pytest.fixture(scope="module")
def planar(tmp_path_factory):
    path = tmp_path_factory.mktemp("planar") / "planar.csv.gz"
    simulate(30.0, 42, coverage="planar", motor=False).track.write(path)
    return path


def test_coverage_title_clears_the_subplot_titles(hemisphere):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from streamcal.report.figures import FigureData, coverage_figure

    track = Track.read(hemisphere)
    fig = coverage_figure(FigureData.build(track, diagnose(track, calibration=fit(
        simulate(30.0, 42, motor=False).track))))
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    title = fig._suptitle
    assert title.get_text().count("\n") >= 2          # a long hint: the case that overlapped
    top = title.get_window_extent(renderer)
    for ax in fig.axes:
        if ax.get_title():
            assert ax.title.get_window_extent(renderer).y1 < top.y0, ax.get_title()


def test_a_refused_track_is_reported_and_the_page_says_why(planar, tmp_path, capsys):
    out = tmp_path / "refused.html"
    assert main(["report", str(planar), "-o", str(out)]) == 1
    page = out.read_text()
    for png in _images(page):
        _assert_not_blank(png)
    _assert_self_contained(page)
    err = capsys.readouterr().err
    reason = err.split("no calibration: ", 1)[1].split(" (the report", 1)[0]
    assert 'class="box refused"' in page and reason in html.unescape(page)


def test_a_cap_against_its_full_calibration():
    """25 s at 1.5 µT noise (the real track's 3 %): a cap too short to determine K."""
    check_cap_against_its_full_calibration(simulate(25.0, 44, motor=False, noise_uT=1.5).track)
