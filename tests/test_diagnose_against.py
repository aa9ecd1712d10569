"""Diagnosis against a calibration the user already holds, on slices of the sphere (issue #10)."""
import json

import numpy as np
import pytest

import streamcal
from streamcal.cli import main
from streamcal.errors import InsufficientDataError
from streamcal.inputs.track import Track
from streamcal.sim import simulate

#: (e) the held diagnosis of a 15 % cap may be at most this factor above the full fit's rms.
REAL_RMS_FACTOR = 1.5


@pytest.fixture(scope="module")
def full_and_slice():
    """A full-sphere recording fitted, and a ±10° band of the same board with a motor-current
    field (2 µT/A) that the first recording lacks."""
    full = simulate(60, seed=1, temp_profile="constant")
    cal = streamcal.fit(full.track)
    sl = simulate(40, seed=2, effects={"aux_interference": 2.0}, coverage="band", band_deg=10,
                  temp_profile="constant", K=full.truth.K, b=full.truth.b)
    return cal, sl.track


def test_slice_refused_by_a_fresh_fit(full_and_slice):
    _, track = full_and_slice
    with pytest.raises(InsufficientDataError):
        streamcal.fit(track)


def test_against_calibration_finds_the_motor(full_and_slice):
    cal, track = full_and_slice
    d = streamcal.diagnose(track, calibration=cal, calibration_source="bench.json")
    top = d.candidates[0]
    assert top.effect == "aux_interference" and top.significant
    assert "motor_current" in top.evidence
    assert top.rms_after < d.rms
    assert d.verdict == "effect_missing"
    out = d.to_dict()
    assert out["calibration_source"] == "bench.json"
    assert out["held"], "a ±10° band cannot determine every entry of K"
    for name, est in out["estimated"].items():
        assert name not in out["held"]
        assert est["sigma"] > 0 and np.isfinite(est["value"])
    json.dumps(out, allow_nan=False, default=lambda v: None)


def test_slice_without_calibration_is_not_refused(full_and_slice):
    _, track = full_and_slice
    d = streamcal.diagnose(track)
    assert d.held.parameters and "default" in d.held.calibration_source
    assert set(["b_x", "b_y", "b_z"]) <= set(d.held.estimated)
    assert d.candidates[0].effect == "aux_interference"


def test_short_noisy_slice_is_refused_saying_what_would_answer():
    sl = simulate(2, seed=3, coverage="band", band_deg=5, noise_uT=8.0, temp_profile="constant",
                  motor=False)
    with pytest.raises(InsufficientDataError) as exc:
        streamcal.diagnose(sl.track)
    msg = str(exc.value)
    assert "samples at this noise" in msg and "--cal" in msg and "tolerance" in msg


def test_cal_that_is_not_a_calibration_exits_2(tmp_path, capsys, full_and_slice):
    _, track = full_and_slice
    path = tmp_path / "slice.csv"
    track.write(path)
    bogus = tmp_path / "notes.json"
    bogus.write_text('{"hello": 1}\n')
    assert main(["diagnose", str(path), "--cal", str(bogus)]) == 2
    assert str(bogus) in capsys.readouterr().err


@pytest.mark.slow
def test_cli_diagnose_and_report_with_cal(tmp_path, capsys, full_and_slice):
    cal, track = full_and_slice
    path, cal_path = tmp_path / "slice.csv", tmp_path / "cal.json"
    track.write(path)
    cal.save(cal_path)
    assert main(["diagnose", str(path), "--cal", str(cal_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["calibration_source"] == str(cal_path)
    assert out["candidates"][0]["effect"] == "aux_interference"
    assert main(["diagnose", str(path), "--cal", str(cal_path)]) == 0
    text = capsys.readouterr().out
    assert "held" in text and "re-estimated" in text
    # a state directory: its calibration.json
    state = tmp_path / "state"
    state.mkdir()
    cal.save(state / "calibration.json")
    html = tmp_path / "r.html"
    assert main(["report", str(path), "--cal", str(state), "-o", str(html)]) == 0
    assert html.stat().st_size > 0


def test_fit_initial_warm_start(tmp_path, capsys, full_and_slice):
    cal, _ = full_and_slice
    full = simulate(60, seed=1, temp_profile="constant")
    path, cal_path = tmp_path / "full.csv", tmp_path / "cal.json"
    full.track.write(path)
    cal.save(cal_path)
    assert main(["fit", str(path), "--initial", str(cal_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.allclose(out["b"], cal.b, atol=0.05)


def check_cap_against_its_full_calibration(track) -> None:
    """A cap of 15 % of the sphere cut from ``track``: too little to fit K, but diagnosed
    against the full track's calibration (or with K = r·I held) within
    :data:`REAL_RMS_FACTOR` of that calibration's rms."""
    cal = streamcal.fit(track)
    x = cal.apply(track.mag)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    centre = x.mean(axis=0)
    centre /= np.linalg.norm(centre)
    in_cap = x @ centre >= 0.7             # a cap of (1 − 0.7)/2 = 15 % of the sphere
    keep = ~np.asarray(track.mag_rows, bool)
    keep[np.flatnonzero(track.mag_rows)[in_cap]] = True
    cap = track.select(keep)
    assert 100 < len(cap.mag) < len(track.mag)
    with pytest.raises(InsufficientDataError):
        streamcal.fit(cap)
    d = streamcal.diagnose(cap, calibration=cal)
    assert d.held.parameters
    assert d.rms <= REAL_RMS_FACTOR * cal.rms, (d.rms, cal.rms)
    # without the calibration: b from the cap, K = r·I held
    d0 = streamcal.diagnose(cap)
    assert {"K_xx", "K_yy", "K_zz"} <= set(d0.held.parameters)
    assert {"b_x", "b_y", "b_z"} <= set(d0.held.estimated)
    assert d0.rms <= REAL_RMS_FACTOR * cal.rms, (d0.rms, cal.rms)


def test_real_cap_against_its_full_calibration(real_tracks_dir):
    check_cap_against_its_full_calibration(
        Track.read(real_tracks_dir / "tiva_mpu9250_mag_03.csv"))


def test_state_dir_falls_back_to_history(tmp_path, full_and_slice):
    from streamcal.cli._calarg import load_calibration_arg
    from streamcal.errors import CalibrationFileError

    cal, _ = full_and_slice
    state = tmp_path / "state"
    (state / "history").mkdir(parents=True)
    cal.save(state / "history" / "0001.json")
    (state / "calibration.json").write_text("{ damaged")
    loaded, source = load_calibration_arg(str(state))
    assert source.endswith("0001.json") and np.allclose(loaded.K, cal.K)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CalibrationFileError, match="no usable calibration"):
        load_calibration_arg(str(empty))


def test_full_sphere_without_cal_is_the_fresh_diagnosis():
    from streamcal.diagnosis.diagnosis import diagnose as fresh

    track = simulate(20, seed=4, temp_profile="constant").track
    d = streamcal.diagnose(track, ladder=False)
    assert d.held is None and "held" not in d.to_dict()
    advice = ("summary", "next_step", "heading_error_deg", "heading_error_reason")
    engine = {k: v for k, v in d.to_dict().items() if k not in advice}
    assert engine == {k: v for k, v in fresh(track, ladder=False).to_dict().items()
                      if k not in advice}
