"""Speed-ups of the gravity-tied fit for long-log diagnosis (issue #13 item 2): the down
direction cached per lag is the interpolated one and cannot be altered through the cache; a
ranking fit stopped at a looser ``rtol`` takes fewer LM steps and lands close to the converged
fit."""
import numpy as np
import pytest

from streamcal.fitting import fit
from streamcal.fitting.registration import _Problem, gravity_reference, registration_fit
from streamcal.sim import simulate

BASE = ("hard_iron", "soft_iron")


@pytest.fixture(scope="module")
def track():
    return simulate(60.0, 5, effects={"mag_accel_misalignment": 0.04}, noise_uT=0.4).track


def test_cached_down_equals_the_interpolated_one_and_is_read_only(track):
    gref = gravity_reference(track)
    cov = {k: np.asarray(v, float) for k, v in track.covariates_at_mag().items()}
    prob = _Problem(np.asarray(track.mag, float), cov, gref, [], False, True)
    for lag in (0.0, 0.02, -0.01, 0.0, 0.03, 0.04, 0.05, 0.0):   # more lags than the cache holds
        g, trust = prob.down(lag)
        want_g, want_trust = gref.at(cov["t"] - lag)
        np.testing.assert_array_equal(g, want_g)
        np.testing.assert_array_equal(trust, want_trust)
        with pytest.raises(ValueError):
            g[0, 0] = 1.0
    assert prob.down(0.05)[0] is prob.down(0.05)[0]


def test_a_looser_rtol_stops_earlier_and_stays_close(track):
    gref = gravity_reference(track)
    base = fit(track, model=BASE)
    model = (*BASE, "mag_accel_misalignment")
    tight = registration_fit(track, model, initial=base, gref=gref)
    loose = registration_fit(track, model, initial=base, gref=gref, rtol=1e-4)
    assert loose.iterations <= tight.iterations
    assert abs(loose.rms - tight.rms) <= 0.01 * tight.rms
    assert np.degrees(np.linalg.norm(loose.rotation @ tight.rotation.T - np.eye(3))) < 0.5
