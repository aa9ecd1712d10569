"""Long-recording diagnosis from a stratified subsample (streamcal.diagnosis.subsample): the
sample keeps every visited sphere cell and the whole time span, the verdict and top candidate
agree with the full computation on hidden-effect tracks, and the output says what was used."""
import json

import numpy as np
import pytest

from streamcal.diagnosis import diagnose
from streamcal.diagnosis.subsample import StratifiedSampler, diagnose_chunks, diagnose_file
from streamcal.sim import simulate
from tests._diagnose_helpers import fitter


def _chunks(track, rows=7000):
    return (track.select(slice(a, a + rows)) for a in range(0, len(track), rows))


def _sampler():
    return StratifiedSampler(time_bins=6, per_bin=8, n_cells=60)


def test_sample_keeps_every_cell_and_the_whole_span():
    track = simulate(240.0, 5, noise_uT=0.4).track
    s = _sampler()
    for c in _chunks(track):
        s.add(c)
    s.finish()
    sub = s.track()
    assert 0 < len(sub.mag) < 0.5 * len(track.mag) and s.samples_total == len(track.mag)
    # every cell a block visited (block-mean directions about the final centre) keeps a block
    visited = set(s.best[:, 0].astype(int))
    kept = set(s.meta[:, 2].astype(int)) | visited
    assert visited <= kept and len(visited) > 20
    # every time bin of the span holds samples
    t = sub.t_mag
    bins = np.floor((t - track.t_mag[0]) / s.width).astype(int)
    full_bins = np.floor((track.t_mag - track.t_mag[0]) / s.width).astype(int)
    assert set(bins) == set(full_bins)
    # time order, rows copied whole (IMU rows between the magnetometer rows stay)
    assert np.all(np.diff(sub.t) >= 0) and sub.has("gyro") and sub.has("accel")
    # reproducible
    s2 = _sampler()
    for c in _chunks(track, 5000):
        s2.add(c)
    s2.finish()
    np.testing.assert_array_equal(s2.track().t, sub.t)


@pytest.mark.parametrize("effect, magnitude, seed, noise",
                         [("temperature_offset", 0.6, 11, 0.4), ("time_drift", 0.05, 13, 0.5)])
@pytest.mark.slow
def test_subsample_agrees_with_the_full_diagnosis(effect, magnitude, seed, noise):
    track = simulate(240.0, seed, effects={effect: magnitude}, noise_uT=noise).track
    full = diagnose(track, fitter=fitter, ladder=False)
    sub = diagnose_chunks(_chunks(track), fitter=fitter, ladder=False, sampler=_sampler())
    assert sub.sampling["samples_used"] < 0.5 * sub.sampling["samples_total"]
    assert (sub.verdict, sub.candidates[0].effect) == (full.verdict, full.candidates[0].effect)
    assert sub.candidates[0].effect == effect


@pytest.mark.slow
def test_a_hidden_lag_on_a_subsample_is_judged_as_on_the_whole_recording():
    """The gravity reference of a subsample is built on the chunks read, not across the gaps
    between kept blocks: the gravity-tied numbers, the verdict and the top candidate are those
    of the full computation (across the gaps the tied rms was ≈ 25 µT for ≈ 1.1 µT)."""
    track = simulate(240.0, 41, effects={"time_lag": 0.02}).track
    full = diagnose(track, fitter=fitter, ladder=False)
    sub = diagnose_chunks(_chunks(track), fitter=fitter, ladder=False, sampler=_sampler())
    assert sub.sampling["samples_used"] < 0.5 * sub.sampling["samples_total"]
    assert (sub.verdict, sub.candidates[0].effect) == (full.verdict, full.candidates[0].effect)
    assert full.candidates[0].effect == "time_lag" and full.verdict == "effect_missing"
    a, b = full.candidates[0], sub.candidates[0]
    assert b.residual == "gravity_tied"
    assert b.rms_before == pytest.approx(a.rms_before, rel=0.1)
    assert b.rms_after == pytest.approx(a.rms_after, rel=0.1)
    assert sub.floor_for("gravity_tied") == pytest.approx(full.floor_for("gravity_tied"), rel=0.25)
    # the horizontal field behind the heading error uses the same reference (dip ≈ 60°), and
    # so does the comparison with the local field (diagnose --lat/--lon)
    assert sub.heading_error_deg["H_uT"] == pytest.approx(full.heading_error_deg["H_uT"],
                                                          rel=0.05)
    from streamcal.diagnosis.reference_field import fitted_dip

    dip, _ = fitted_dip(sub.subsample, sub.calibration, sub.gravity)
    assert dip == pytest.approx(fitted_dip(track, full.calibration)[0], abs=1.0)


@pytest.mark.slow
def test_file_path_spans_over_the_whole_recording_and_json_says_so(tmp_path):
    res = simulate(240.0, 31, outlier_bursts=2, noise_uT=0.4)
    path = tmp_path / "long.csv"
    res.track.write(path)
    d = diagnose_file(path, fitter=fitter, ladder=False, rows=9000, sampler=_sampler())
    out = json.loads(json.dumps(d.to_dict()))
    assert out["samples_total"] == len(res.track.mag) > out["samples_used"] > 0
    assert "stratified" in out["subsample_rule"] and out["outlier_spans_over"] == "recording"
    # each true burst is inside a reported span
    for a, b in res.truth.outlier_spans:
        mid = 0.5 * (a + b)
        assert any(lo <= mid <= hi for lo, hi in out["outlier_spans"]), out["outlier_spans"]
    # the ordinary path says it used every sample
    small = diagnose(res.track.select(slice(0, 6000)), fitter=fitter, ladder=False).to_dict()
    assert small["samples_used"] == small["samples_total"] == small["n"]
    assert small["subsample_rule"] == "every sample"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["track.csv", "track.csv.gz"])
def test_cli_takes_the_subsample_above_the_sample_count_and_full_says_every_sample(
        tmp_path, monkeypatch, capsys, name):
    """Decided by the number of magnetometer samples, the same for any file format."""
    from streamcal.cli import main
    from streamcal.diagnosis import subsample

    path = tmp_path / name
    simulate(120.0, 7, noise_uT=0.4).track.write(path)
    monkeypatch.setattr(subsample, "LONG_SAMPLES", 5000)
    assert main(["diagnose", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples_used"] < out["samples_total"] and "stratified" in out["subsample_rule"]
    assert main(["diagnose", str(path), "--json", "--full"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples_used"] == out["samples_total"] == out["n"]
    assert main(["diagnose", str(path)]) == 0
    assert "magnetometer samples (stratified" in capsys.readouterr().out


@pytest.mark.slow
def test_against_a_calibration_a_long_recording_is_subsampled_too(tmp_path, monkeypatch, capsys):
    from streamcal.calibration import Calibration
    from streamcal.cli import main
    from streamcal.diagnosis import subsample

    res = simulate(120.0, 8, noise_uT=0.4)
    path, cal = tmp_path / "track.csv.gz", tmp_path / "cal.json"
    res.track.write(path)
    Calibration(K=res.truth.K, b=res.truth.b).save(cal)
    monkeypatch.setattr(subsample, "LONG_SAMPLES", 5000)
    assert main(["diagnose", str(path), "--cal", str(cal), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples_used"] < out["samples_total"] and out["held"] is not None
