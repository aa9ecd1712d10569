"""Every rms of a diagnosis is shown against the rms it is compared with *on the same residual*:
the ladder figure gives each residual family (sensor, gravity-tied, gyro-tied) its own panel,
"model now" line and noise level, the ladder marks the switch to a tied residual, the HTML and
terminal tables name the residual of every row; and the outlier count, spans and mask of a
diagnosis come from one model (``outliers_model``)."""
import json
import re

import numpy as np
import pytest
from matplotlib.colors import to_rgba

from streamcal.cli.diagnose import _text
from streamcal.diagnosis import diagnose, outlier_spans
from streamcal.report import FigureData, render_figures, render_html
from streamcal.report.figures_ladder import (RESIDUAL_FAMILIES, candidate_groups, ladder_figure,
                                             ladder_steps)
from streamcal.sim import simulate
from streamcal.values import thaw

MISALIGNED = "mag_accel_misalignment"
SPEC_CANDIDATE_KEYS = {"effect", "rms_after", "p_value", "evidence", "residual", "rms_before",
                       "significant", "material", "n"}


@pytest.fixture(scope="module")
def tied():
    """A hidden misalignment: the ladder's second step is on the gravity-tied residual, whose
    rms (≈ 0.8 µT) is above the base model's sensor rms (≈ 0.4 µT) although it is a fall."""
    track = simulate(40.0, 51, effects={MISALIGNED: 0.06}).track
    return track, diagnose(track, candidates=[MISALIGNED, "time_drift"])


@pytest.fixture(scope="module")
def hidden():
    """A hidden temperature offset and one outlier burst."""
    track = simulate(40.0, 11, effects={"temperature_offset": 0.6}, outlier_bursts=1).track
    return track, diagnose(track, candidates=["temperature_offset", "time_drift"])


def _panels(fig):
    """{residual family: axes} of the candidate panels (found by their title)."""
    out = {}
    for ax in fig.axes[1:]:
        for name, (label, *_rest) in RESIDUAL_FAMILIES.items():
            if label + ":" in ax.get_title():
                out[name] = ax
    return out


def _black_lines(ax):
    return [ln.get_xdata()[0] for ln in ax.lines
            if to_rgba(ln.get_color()) == to_rgba("k") and len(ln.get_xdata()) == 2
            and ln.get_xdata()[0] == ln.get_xdata()[1]]


def test_each_candidate_carries_the_residual_and_rms_it_is_compared_with(tied):
    _, d = tied
    assert d.verdict == "effect_missing" and d.candidates[0].effect == MISALIGNED
    base = d.candidate_baselines()
    assert base[MISALIGNED]["residual"] == "gravity_tied"
    assert base["time_drift"] == {"residual": "sensor", "rms_before": d.rms}
    tied_before = base[MISALIGNED]["rms_before"]
    # the misleading comparison the pictures must not make: rms_after is above the sensor rms
    assert d.candidates[0].rms_after > d.rms
    assert d.candidates[0].rms_after < 0.9 * tied_before      # a fall on its own residual
    out = json.loads(json.dumps(d.to_dict()))
    for c in out["candidates"]:                               # SPEC §4 keys untouched
        assert set(c) == SPEC_CANDIDATE_KEYS
    assert out["residual"] == "sensor"
    assert out["candidate_baselines"][MISALIGNED]["rms_before"] == pytest.approx(tied_before)
    step = out["ladder"][1]
    assert step["residual"] == "gravity_tied"
    assert step["rms_before"] == pytest.approx(tied_before) and step["rms"] < step["rms_before"]


def test_ladder_figure_gives_each_residual_its_own_panel_and_base_line(tied):
    track, d = tied
    fig = ladder_figure(FigureData.build(track, d))
    panels = _panels(fig)
    assert set(panels) == {"sensor", "gravity_tied"}
    groups = {name: (before, [c.effect for c in cands]) for name, before, cands in
              candidate_groups(d)}
    for name, ax in panels.items():
        before, effects = groups[name]
        labels = [t.get_text() for t in ax.get_yticklabels()]
        assert sorted(labels) == sorted(effects)              # no panel mixes residuals
        assert _black_lines(ax) == [pytest.approx(before)]    # its own "model now"
        widths = sorted(p.get_width() for p in ax.patches)
        expected = sorted(c.rms_after for c in d.candidates if c.effect in effects)
        assert widths == pytest.approx(expected)
        floor = RESIDUAL_FAMILIES[name][3] * d.noise_floor    # its own noise level
        xs = [ln.get_xdata()[0] for ln in ax.lines if ln.get_linestyle() in ("--", ":")]
        assert xs == [pytest.approx(floor)]
        lo, hi = ax.get_xlim()
        assert lo == 0 and hi > max(expected + [before, floor])
    assert groups["sensor"][0] == pytest.approx(d.rms)
    assert groups["gravity_tied"][0] > 1.5 * d.rms           # really another scale


def test_ladder_panel_draws_the_tied_step_from_the_same_model_on_its_residual(tied):
    track, d = tied
    steps = ladder_steps(d)
    assert [s["residual"] for s in steps] == ["sensor", "gravity_tied"]
    ax = ladder_figure(FigureData.build(track, d)).axes[0]
    segments = [(tuple(ln.get_xdata()), tuple(ln.get_ydata())) for ln in ax.lines
                if len(ln.get_xdata()) == 2]
    # the step's line starts at the same model on the gravity-tied residual, not at the
    # sensor rms of step 0; a dotted connector shows the switch
    assert ((0, 1), (pytest.approx(steps[1]["rms_before"]), pytest.approx(steps[1]["rms"]))) \
        in segments
    assert ((0, 0), (pytest.approx(steps[0]["rms"]), pytest.approx(steps[1]["rms_before"]))) \
        in segments
    assert not any(y == (pytest.approx(steps[0]["rms"]), pytest.approx(steps[1]["rms"]))
                   for _, y in segments)
    texts = " ".join(t.get_text() for t in ax.texts)
    assert "same model on the gravity-tied residual" in texts
    pct = round(100 * (steps[1]["rms"] / steps[1]["rms_before"] - 1))
    assert f"−{abs(pct)} %" in texts and pct < 0


@pytest.mark.slow
def test_html_and_terminal_tables_name_the_residual_of_every_row(tied):
    track, d = tied
    page = render_html(track, d)
    table = page.split("<h2>Candidate effects</h2>", 1)[1].split("<h2>", 1)[0]
    rows = {r.split("</td>", 1)[0].removeprefix("<td>"): r
            for r in re.findall(r"<tr>(<td>.*?)</tr>", table)}
    tied_row, sensor_row = rows[MISALIGNED], rows["time_drift"]
    assert "gravity-tied residual" in tied_row and "sensor residual" in sensor_row
    before = d.baseline(d.candidates[0])[1]
    assert f"{before:.4g}" in tied_row
    cells = [c.split(">", 1)[1] for c in tied_row.split("</td>") if "<td" in c]
    # "× floor" on a tied residual is against that residual's own floor, not the sensor's
    tied_floor = d.floor_for("gravity_tied")
    assert cells[5] == f"{d.candidates[0].rms_after / tied_floor:.2f}"
    summary = page.split('class="box missing"', 1)[1].split("</div>", 1)[0]
    assert "gravity-tied residual" in summary and f"{before:.3g}" in summary   # 3 digits there
    text = _text(d)
    line = next(s for s in text.splitlines() if s.startswith(MISALIGNED))
    assert "gravity-tied" in line and f"{before:.4g}" in line
    step = next(s for s in text.splitlines() if s.startswith("+ " + MISALIGNED))
    tied_step = next(s for s in d.ladder if s.get("added") == MISALIGNED)
    assert step.split()[-2] == f"{tied_step['rms'] / tied_floor:.2f}"   # then the outliers


@pytest.mark.slow
def test_outlier_count_spans_and_mask_come_from_one_model(hidden):
    track, d = hidden
    assert d.outliers_model == ("hard_iron", "soft_iron", "temperature_offset")
    assert d.ladder[-1]["model"] == d.outliers_model
    top = d.candidates[0].calibration                        # that model, fitted on every sample
    assert np.array_equal(d.outliers, ~np.asarray(top.inliers, bool))
    assert d.n_outliers_model == int(d.outliers.sum()) > 0
    assert thaw(d.outlier_spans) == outlier_spans(track.t_mag, d.outliers)
    assert d.to_dict()["outliers_model"] == list(d.outliers_model)
    assert d.to_dict()["n_outliers_model"] == d.n_outliers_model
    # n_outliers stays with model and rms (SPEC §4): the base model's
    assert d.n_outliers == int((~np.asarray(d.calibration.inliers, bool)).sum())
    assert d.to_dict()["n_outliers"] == d.n_outliers
    t = np.asarray(track.t_mag)
    inside = np.zeros(len(t), bool)
    for a, b in d.outlier_spans:
        inside |= (t >= a) & (t <= b)
    assert (d.outliers & inside).sum() >= 0.95 * d.n_outliers_model
    data = FigureData.build(track, d)                        # the figures mark the same ones
    assert np.array_equal(data.inliers, ~d.outliers)
    page = render_html(track, d)
    assert f"<b>{d.n_outliers_model}</b> of {d.n} samples are outliers of the last model of " \
           f"the ladder, <code>{', '.join(d.outliers_model)}</code>" in page
    assert d.ladder[-1]["n_outliers"] == d.n_outliers_model   # the same count the ladder shows


def test_without_a_ladder_outliers_are_the_base_models(hidden):
    track, _ = hidden
    d = diagnose(track, candidates=["temperature_offset"], ladder=False)
    assert d.outliers_model == ("hard_iron", "soft_iron")
    assert np.array_equal(d.outliers, ~np.asarray(d.calibration.inliers, bool))
    assert d.n_outliers == d.n_outliers_model == int(d.outliers.sum())


@pytest.mark.slow
def test_ladder_png_is_byte_identical(tied):
    track, d = tied
    a = {f.name: f.png for f in render_figures(FigureData.build(track, d))}
    b = {f.name: f.png for f in render_figures(FigureData.build(track, d))}
    assert a["ladder"] == b["ladder"] and a == b
    assert a["ladder"].startswith(b"\x89PNG\r\n\x1a\n")
