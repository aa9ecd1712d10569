"""Diagnosis with the registration candidates: a hidden misalignment or time lag is found and
its promise kept (gravity-tied with an accelerometer, gyro-tied without); clean gyro-only tracks
raise no false alarm; the gyro-consistency family is in the JSON; the bundled demo track's
outlier spans are only its real burst; the spread subset used for the ranking keeps the promised
rms_after close to a full refit."""
import json

import pytest

from streamcal.diagnosis import diagnose
from streamcal.fitting import fit
from streamcal.fitting.registration import registration_fit
from streamcal.sim import simulate
from tests._diagnose_helpers import fitter
from tests.test_gyro_lag import LAG_TOL, without_accel

DURATION = 40.0
BASE = ("hard_iron", "soft_iron")
#: (effect, magnitude, seed): rad for the rotation, s for the lag — a few times what the
#: gravity reference's error (≈ 1.3°) hides.
HIDDEN = [("mag_accel_misalignment", 0.06, 51), ("time_lag", 0.03, 52), ("time_lag", -0.02, 53)]


@pytest.mark.parametrize("effect, magnitude, seed", HIDDEN)
def test_hidden_registration_effect_is_found_and_promise_is_kept(effect, magnitude, seed):
    track = simulate(DURATION, seed, effects={effect: magnitude}).track
    d = diagnose(track, fitter=fitter, ladder=False)
    assert d.verdict == "effect_missing"
    top = d.candidates[0]
    assert top.effect == effect, [c.to_dict() for c in d.candidates]
    assert "gravity-tied rms" in top.evidence
    after = registration_fit(track, (*BASE, effect))          # "add it and refit"
    clean = simulate(DURATION, seed).track                     # same motion and noise, no effect
    assert after.rms <= 1.15 * registration_fit(clean, (*BASE, effect)).rms
    assert abs(top.rms_after - after.rms) <= 0.2 * after.rms


#: (τ s, seed) hidden in mag + gyro tracks (no accelerometer).
HIDDEN_GYRO = [(0.03, 52), (-0.02, 53), (0.012, 54)]


@pytest.mark.slow
@pytest.mark.parametrize("tau, seed", HIDDEN_GYRO)
def test_hidden_lag_is_found_from_the_gyro_alone(tau, seed):
    track = without_accel(simulate(DURATION, seed, effects={"time_lag": tau}).track)
    d = diagnose(track, fitter=fitter, ladder=False)
    assert d.verdict == "effect_missing"
    top = d.candidates[0]
    assert top.effect == "time_lag", [c.to_dict() for c in d.candidates]
    assert "gyro-tied rms" in top.evidence and "the gyro by" in top.evidence
    assert top.calibration.effects["time_lag"]["tau"] == pytest.approx(tau, abs=LAG_TOL)
    after = fit(track, model=(*BASE, "time_lag"))             # "add it and refit"
    assert abs(top.rms_after - after.rms) <= 0.2 * after.rms
    clean = without_accel(simulate(DURATION, seed).track)     # same motion and noise, no lag
    assert after.rms <= 1.15 * fit(clean, model=(*BASE, "time_lag")).rms
    gyro = d.residual_families["gyro"]                         # the model without the lag
    assert gyro["lag_s"] == 0.0 and gyro["rms"] > 1.05 * after.rms
    assert gyro["lag_estimate_s"] == pytest.approx(tau, abs=LAG_TOL)


def test_gyro_family_is_in_the_json_and_follows_the_model():
    track = without_accel(simulate(30.0, 44, effects={"time_lag": 0.02}).track)
    out = json.loads(json.dumps(diagnose(track, fitter=fitter, candidates=[]).to_dict()))
    fam = out["residual_families"]["gyro"]
    assert fam["unit"] == "sensor" and fam["horizon_s"] == pytest.approx(0.5, abs=0.02)
    assert fam["n"] > 0.9 * out["n"] and {"t", "direction"} <= set(fam["by"])
    with_lag = diagnose(track, model=(*BASE, "time_lag"), fitter=fitter, candidates=[])
    fam2 = with_lag.residual_families["gyro"]
    assert fam2["lag_s"] == pytest.approx(0.02, abs=LAG_TOL)
    assert fam2["rms"] < 0.9 * fam["rms"]              # the lag explained what the gyro saw


@pytest.mark.slow
def test_clean_gyro_only_tracks_raise_no_false_alarm():
    verdicts, lag_flags = [], 0
    for k, seed in enumerate(range(200, 220)):
        track = without_accel(simulate(30.0, seed, noise_uT=(0.2, 0.4, 0.7)[k % 3],
                                       mag_bits=(16, 14)[k % 2],
                                       rate_rad_s=(1.0, 1.5, 2.5)[k % 3]).track)
        d = diagnose(track, fitter=fitter, ladder=False)
        verdicts.append(d.verdict)
        lag = [c for c in d.candidates if c.effect == "time_lag"]
        assert lag, "time_lag must be a candidate on a gyro track"
        lag_flags += lag[0].significant
    assert verdicts.count("at_noise_floor") >= 19, verdicts
    assert lag_flags <= 1


@pytest.mark.slow
def test_demo_track_spans_are_only_the_real_burst(demo_track):
    d = diagnose(demo_track, fitter=fitter, candidates=["temperature_offset", "time_drift"])
    assert d.verdict == "effect_missing"
    assert len(d.outlier_spans) == 1, d.outlier_spans
    (s, e), = d.outlier_spans
    assert 50.9 - 1.0 <= s and e <= 55.4 + 1.0 and e - s > 1.0


@pytest.fixture(scope="module")
def demo_track():
    from importlib.resources import files

    from streamcal.inputs.track import Track

    return Track.read(files("streamcal") / "data" / "demo_track.csv.gz")


@pytest.mark.slow
def test_subset_ranking_promises_within_20_percent_of_full_refits():
    track = simulate(90.0, 61, effects={"temperature_offset": 0.4}).track
    names = ["temperature_offset", "time_drift", "temperature_scale"]
    quick = diagnose(track, fitter=fitter, candidates=names, ladder=False, subset_max=3000)
    full = diagnose(track, fitter=fitter, candidates=names, ladder=False, subset_max=None)
    assert [c.effect for c in quick.candidates][:1] == [c.effect for c in full.candidates][:1]
    by_name = {c.effect: c.rms_after for c in full.candidates}
    for c in quick.candidates:
        assert abs(c.rms_after - by_name[c.effect]) <= 0.2 * by_name[c.effect], c.effect
