"""AcceptanceGuard: sanity limits and the held-out comparison, each with a named reason."""
import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.stream.guard import AcceptanceGuard, Decision

RNG = np.random.default_rng(11)
TRUE_K = np.array([[50.0, 1.0, -0.5], [0.0, 47.0, 0.8], [0.0, 0.0, 53.0]])
TRUE_B = np.array([12.0, -25.0, 40.0])


def _samples(n, noise=0.3):
    d = RNG.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ TRUE_K.T + TRUE_B + RNG.normal(scale=noise, size=(n, 3))


def _cal(K=TRUE_K, b=TRUE_B, rms=0.3, unit="uT"):
    return Calibration(K=K, b=b, rms=rms, n=1000, unit=unit)


def test_worse_candidate_is_rejected_with_reason():
    holdout = _samples(200)
    current = _cal()
    worse = _cal(b=TRUE_B + [2.0, 0.0, 0.0])
    d = AcceptanceGuard().check(worse, holdout, current=current)
    assert not d.accepted and d.reason == "worse_on_holdout"
    assert d.value > d.limit
    assert d.details["current_error"] < d.limit
    assert "worse_on_holdout" in str(d) and f"{d.limit:.4g}" in str(d)


def test_better_candidate_is_accepted():
    holdout = _samples(200)
    stale = _cal(b=TRUE_B + [3.0, -2.0, 0.0])
    d = AcceptanceGuard().check(_cal(), holdout, current=stale)
    assert d.accepted and d.reason == "better_on_holdout" and d.value <= d.limit


def test_equal_quality_refit_is_not_rejected_by_noise():
    holdout = _samples(100)
    twin = _cal(b=TRUE_B + [0.02, -0.01, 0.0])
    assert AcceptanceGuard().check(twin, holdout, current=_cal()).accepted


def test_first_calibration_needs_only_sanity():
    d = AcceptanceGuard().check(_cal(), _samples(50))
    assert d.accepted and d.reason == "first_calibration"


@pytest.mark.parametrize("cand, reason, value, limit", [
    (_cal(K=TRUE_K * 3), "field_out_of_range", None, 100.0),
    (_cal(K=TRUE_K / 5), "field_out_of_range", None, 15.0),
    (_cal(b=[1500.0, 0, 0]), "offset_too_large", 1500.0, 1000.0),
    (_cal(K=np.diag([12.0, 50.0, 95.0])), "ill_conditioned", 95.0 / 12.0, 5.0),
    (_cal(rms=float("nan")), "rms_not_finite", None, None),
    (_cal(rms=20.0), "rms_too_large", 20.0, None),
])
def test_insane_candidates_are_rejected(cand, reason, value, limit):
    d = AcceptanceGuard().check(cand, _samples(100), current=_cal())
    assert not d.accepted and d.reason == reason
    if value is not None:
        assert d.value == pytest.approx(value, rel=1e-6)
    if limit is not None:
        assert d.limit == pytest.approx(limit)


def test_other_units_are_judged_relative_to_the_sphere_estimate():
    cand = _cal(K=TRUE_K * 10, b=TRUE_B * 10, rms=3.0, unit="counts")
    holdout = _samples(100) * 10
    assert AcceptanceGuard().check(cand, holdout, reference_radius=500.0).accepted
    d = AcceptanceGuard().check(cand, holdout, reference_radius=2000.0)
    assert d.reason == "field_out_of_range" and d.limit == pytest.approx(1000.0)


def test_too_few_holdout_samples():
    d = AcceptanceGuard().check(_cal(), _samples(3), current=_cal())
    assert not d.accepted and d.reason == "too_few_holdout"


def test_decision_to_dict_is_json_ready():
    import json

    d = Decision(False, "worse_on_holdout", 1.92, 1.41, {"n_holdout": 40})
    assert json.loads(json.dumps(d.to_dict())) == {"accepted": False, "reason": "worse_on_holdout",
                                                  "value": 1.92, "limit": 1.41, "n_holdout": 40}
