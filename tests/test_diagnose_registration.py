"""Diagnosis with the registration candidates: a hidden misalignment or time lag is found and
its promise kept; the bundled demo track's outlier spans are only its real burst; the spread
subset used for the ranking keeps the promised rms_after close to a full refit."""
import pytest

from streamcal.diagnose import diagnose
from streamcal.model.registration import registration_fit
from streamcal.sim import simulate
from tests._diagnose_helpers import fitter

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


def test_demo_track_spans_are_only_the_real_burst(demo_track):
    d = diagnose(demo_track, fitter=fitter, candidates=["temperature_offset", "time_drift"])
    assert d.verdict == "effect_missing"
    assert len(d.outlier_spans) == 1, d.outlier_spans
    (s, e), = d.outlier_spans
    assert 50.9 - 1.0 <= s and e <= 55.4 + 1.0 and e - s > 1.0


@pytest.fixture(scope="module")
def demo_track():
    from importlib.resources import files

    from streamcal.track import Track

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
