"""Diagnosis on simulated tracks: hidden effects are found and promised rms_after holds, clean
tracks are at the noise floor, outlier bursts become spans."""
import json

import numpy as np
import pytest

from streamcal.diagnosis import diagnose, noise_floor, outlier_spans
from streamcal.diagnosis.residuals import rms, sensor_residual
from streamcal.sim import simulate
from tests._diagnose_helpers import fitter

DURATION = 60.0
#: (effect, magnitude, seed, noise µT): magnitudes a few times what the noise hides.
HIDDEN = [("temperature_offset", 0.6, 11, 0.4), ("temperature_scale", 0.01, 12, 0.3),
          ("time_drift", 0.05, 13, 0.5), ("aux_interference", 2.0, 14, 0.4),
          ("axis_nonlinearity", 0.1, 15, 0.3)]


def _clean_rms(seed, noise, model=("hard_iron", "soft_iron")):
    track = simulate(DURATION, seed, noise_uT=noise).track
    cal = fitter(track, model)
    r, *_ = sensor_residual(cal, track.mag, track.covariates_at_mag())
    return rms(r, cal.inliers)


@pytest.mark.slow
@pytest.mark.parametrize("effect, magnitude, seed, noise", HIDDEN)
def test_hidden_effect_is_found_and_promise_is_kept(effect, magnitude, seed, noise):
    track = simulate(DURATION, seed, effects={effect: magnitude}, noise_uT=noise).track
    d = diagnose(track, fitter=fitter, ladder=False)
    assert d.verdict == "effect_missing"
    top = d.candidates[0]
    assert top.effect == effect, [c.to_dict() for c in d.candidates]
    after = diagnose(track, model=("hard_iron", "soft_iron", effect), fitter=fitter,
                     candidates=[])
    assert after.rms <= 1.15 * _clean_rms(seed, noise)
    assert abs(top.rms_after - after.rms) <= 0.2 * after.rms
    assert effect in top.evidence or "residual follows" in top.evidence


@pytest.mark.slow
def test_two_hidden_effects_are_found_one_after_the_other():
    track = simulate(DURATION, 21, effects={"time_drift": 0.06, "axis_nonlinearity": 0.12},
                     temp_profile="constant", noise_uT=0.3).track
    d = diagnose(track, fitter=fitter)
    first = d.candidates[0].effect
    assert d.verdict == "effect_missing" and first in ("time_drift", "axis_nonlinearity")
    second = {"time_drift", "axis_nonlinearity"} - {first}
    d2 = diagnose(track, model=("hard_iron", "soft_iron", first), fitter=fitter)
    assert d2.verdict == "effect_missing" and d2.candidates[0].effect in second
    # the ladder walked the same way and ends near the noise floor
    assert [s.get("added") for s in d.ladder[1:3]] == [first, *second]
    assert d.ladder[2]["rms"] <= 1.15 * d.noise_floor


@pytest.mark.slow
def test_clean_tracks_are_at_noise_floor():
    seeds = range(100, 120)
    verdicts = []
    for k, seed in enumerate(seeds):
        track = simulate(30.0, seed, noise_uT=(0.2, 0.4, 0.7)[k % 3], mag_bits=(16, 14)[k % 2],
                         rate_rad_s=(1.0, 1.5, 2.5)[k % 3]).track
        d = diagnose(track, fitter=fitter, ladder=False)
        verdicts.append(d.verdict)
        assert 0.7 * d.noise_floor < d.rms < 1.3 * d.noise_floor
    assert verdicts.count("at_noise_floor") >= 19, verdicts


def test_outlier_bursts_become_spans_and_do_not_inflate_rms():
    res = simulate(DURATION, 31, outlier_bursts=2, noise_uT=0.4)
    d = diagnose(res.track, fitter=fitter, candidates=[])
    truth = res.truth.outlier_spans
    assert len(truth) == 2 and d.n_outliers > 0
    for a, b in truth:
        assert any(s <= b and e >= a for s, e in d.outlier_spans), (truth, d.outlier_spans)
    for s, e in d.outlier_spans:  # every span reported is a true burst
        assert any(s <= b + 1.0 and e >= a - 1.0 for a, b in truth)
    assert d.rms <= 1.15 * _clean_rms(31, 0.4)


def test_json_has_the_spec_keys():
    track = simulate(30.0, 41, effects={"temperature_offset": 0.8}).track
    out = json.loads(json.dumps(diagnose(track, fitter=fitter, ladder=False).to_dict()))
    assert {"model", "n", "n_outliers", "rms", "noise_floor", "verdict", "candidates",
            "outlier_spans"} <= set(out)
    assert out["model"] == ["hard_iron", "soft_iron"]
    for c in out["candidates"]:
        assert set(c) == {"effect", "rms_after", "p_value", "evidence", "residual", "rms_before", "n",
                          "significant", "material"}
        assert c["effect"] not in out["model"]
    rms_after = [c["rms_after"] for c in out["candidates"]]
    assert out["candidates"][0]["rms_after"] == min(rms_after)


def test_noise_floor_matches_known_noise_with_and_without_quantization():
    rng = np.random.default_rng(5)
    n = 20000
    t = np.arange(n) / 100.0
    a1, a2 = 2 * np.sin(0.3 * t) + 0.5 * t, 1.2 * np.sin(0.17 * t + 1)
    x = np.stack([np.sin(a2) * np.cos(a1), np.sin(a2) * np.sin(a1), np.cos(a2)], 1)
    sigma = np.array([0.3, 0.4, 0.5])
    m = x @ (50 * np.eye(3)).T + rng.normal(size=(n, 3)) * sigma
    m[::97] += 40.0  # jumps must not count
    nf = noise_floor(m, t)
    np.testing.assert_allclose(nf.sigma_axes, sigma, rtol=0.05)
    q = np.round(m / 0.6) * 0.6
    nq = noise_floor(q, t)
    np.testing.assert_allclose(nq.lsb, 0.6)
    np.testing.assert_allclose(nq.sigma_axes, np.sqrt(sigma ** 2 + 0.6 ** 2 / 12), rtol=0.06)
    # below the LSB the floor is the quantization noise, not zero
    ramp = np.linspace(10, 16, 500)[:, None] + rng.normal(0, 0.01, (500, 3))
    slow = np.round(ramp / 0.6) * 0.6
    assert noise_floor(slow, np.arange(500) / 100).floor == pytest.approx(0.6 / np.sqrt(12), rel=0.05)


def test_outlier_spans_merge_close_points_and_drop_isolated_ones():
    t = np.arange(0, 30, 0.1)
    out = np.zeros_like(t, bool)
    out[(t > 5) & (t < 6)] = True
    out[(t > 6.8) & (t < 7.2)] = True       # 0.8 s gap: same span
    out[np.argmin(abs(t - 15))] = True      # isolated
    out[(t > 20) & (t < 21)] = True
    assert outlier_spans(t, out) == [[pytest.approx(5.1), pytest.approx(7.1)],
                                     [pytest.approx(20.1), pytest.approx(20.9)]]
    assert outlier_spans(t, np.zeros_like(out)) == []
