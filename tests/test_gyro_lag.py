"""time_lag from the gyro alone (streamcal.fitting.gyro_lag): the analytic Jacobian of the
gyro-tied residual against finite differences, recovery of a simulated lag on tracks without an
accelerometer, the calibration it makes, and what it needs."""
import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.errors import MissingColumnsError
from streamcal.fitting import fit
from streamcal.model import validate_effect_params
from streamcal.fitting.gyro_lag import GyroPairs, gyro_lag_fit, gyro_rates
from streamcal.sim import simulate
from streamcal.inputs.track import Track

BASE = ("hard_iron", "soft_iron")
#: |τ̂ − τ| bound (s): a fifth of the 10 ms magnetometer period. Measured errors on these 40 s
#: tracks are ≤ 0.5 ms; the bound leaves room for the seed-to-seed spread without accepting an
#: estimate that is off by a sample.
LAG_TOL = 0.002


def without_accel(track: Track) -> Track:
    """The same track with the ax, ay, az columns dropped (a mag + gyro recording)."""
    return Track({k: v for k, v in track.columns.items() if k not in ("ax", "ay", "az")},
                 track.metadata)


@pytest.fixture(scope="module")
def lagged():
    return without_accel(simulate(40.0, 7, effects={"time_lag": 0.025}).track)


def test_map_jacobian_matches_finite_differences(lagged):
    cal = fit(lagged, model=BASE)
    x = cal.apply(lagged.mag)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    t_g, w = gyro_rates(lagged)
    pairs = GyroPairs(x[:1500], lagged.t_mag[:1500], cal.K, t_g, w)
    rng = np.random.default_rng(1)
    p0 = np.concatenate([np.eye(3).ravel() + 0.02 * rng.standard_normal(9),
                         0.01 * rng.standard_normal(3)])
    tau = 0.013
    J = pairs.map_jacobian(pairs.orientation(p0), tau)
    for k in range(12):
        step = 1e-6
        pp, pm = p0.copy(), p0.copy()
        pp[k] += step
        pm[k] -= step
        num = (pairs.residual(pairs.orientation(pp), tau)
               - pairs.residual(pairs.orientation(pm), tau)) / (2 * step)
        # the Jacobian integrates Q·δω by trapezoids, the orientation by midpoint steps: equal
        # to second order in the 5 ms IMU step
        np.testing.assert_allclose(J[:, :, k], num, rtol=0, atol=0.01 * np.abs(num).max(),
                                   err_msg=f"parameter {k}")


@pytest.mark.parametrize("tau, seed", [(0.025, 7), (-0.015, 8), (0.0, 9)])
def test_recovers_the_lag_without_accelerometer(tau, seed):
    track = without_accel(simulate(40.0, seed, effects={"time_lag": tau} if tau else {}).track)
    res = gyro_lag_fit(track, (*BASE, "time_lag"))
    assert res.lag == pytest.approx(tau, abs=LAG_TOL)
    base = gyro_lag_fit(track, BASE)
    assert base.lag == 0.0
    if tau:   # the lag is what the gyro-tied residual sees
        assert res.rms < 0.85 * base.rms
    else:     # one parameter more explains (almost) nothing
        assert res.rms > 0.98 * base.rms


def test_gyro_map_absorbs_a_frame_rotation_between_gyro_and_magnetometer(lagged):
    # the gyro turned 90° about z relative to the magnetometer (as on some boards)
    cols = dict(lagged.columns)
    cols["gx"], cols["gy"] = -lagged.columns["gy"], lagged.columns["gx"]
    turned = Track(cols, lagged.metadata)
    res = gyro_lag_fit(turned, (*BASE, "time_lag"))
    assert res.lag == pytest.approx(0.025, abs=LAG_TOL)
    assert res.rms < 1.05 * gyro_lag_fit(lagged, (*BASE, "time_lag")).rms


def test_fit_adds_the_lag_and_the_calibration_round_trips(lagged):
    cal = fit(lagged, model=(*BASE, "time_lag"))
    validate_effect_params(cal.effects)
    assert set(cal.effects) == {"time_lag"}
    assert cal.effects["time_lag"]["tau"] == pytest.approx(0.025, abs=LAG_TOL)
    assert "gyro_tied" in cal.extra and np.isfinite(cal.rms)
    back = Calibration.from_json(cal.to_json())
    assert back.effects == cal.effects and back.model == cal.model
    plain = fit(lagged, model=BASE, kernel="cauchy")   # the lag changes nothing in K, b, apply
    np.testing.assert_allclose(cal.apply(lagged.mag), plain.apply(lagged.mag))


def test_needs_a_gyro_or_an_accelerometer():
    tr = simulate(10.0, 1).track
    mag_only = Track.from_arrays(t=tr.t_mag, mag=tr.mag)
    with pytest.raises(MissingColumnsError, match="gyro"):
        fit(mag_only, model=(*BASE, "time_lag"))
    with pytest.raises(MissingColumnsError):
        gyro_lag_fit(without_accel(tr), (*BASE, "mag_accel_misalignment"))


def test_refuses_a_gyro_that_does_not_follow_the_directions(lagged):
    from streamcal.errors import InsufficientDataError

    cols = dict(lagged.columns)
    for k in ("gx", "gy", "gz"):   # degrees per second read as rad/s: 57× too fast
        cols[k] = np.degrees(lagged.columns[k])
    with pytest.raises(InsufficientDataError, match="gyro gains"):
        gyro_lag_fit(Track(cols, lagged.metadata), (*BASE, "time_lag"))
