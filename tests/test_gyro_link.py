"""The gyro link (issue #10): held parameters pinned by the rotation rate only when that helps."""
import json

import numpy as np
import pytest

import streamcal
from streamcal.calibration import Calibration
from streamcal.cli.diagnose import held_text
from streamcal.diagnosis.held.gyro_guard import P_GUARD
from streamcal.diagnosis.held.fit import TOLERANCE, field_radius
from streamcal.fitting.gyro_rates import gyro_rates
from streamcal.fitting.gyro_link import LinkPairs, link_fit
from streamcal.inputs.track import Track
from streamcal.sim.yaw_slice import yaw_slice

K = np.array([[47.0, 1.2, -0.8], [0.0, 49.0, 0.6], [0.0, 0.0, 46.5]])
B = np.array([12.0, -7.0, 20.0])
TOL = TOLERANCE * field_radius(K)


def _pairs(res, horizon=1.0):
    tr = res.track
    t_g, w_g = gyro_rates(tr)
    return LinkPairs(np.asarray(tr.mag), np.asarray(tr.t_mag), t_g, w_g, horizon)


def test_link_recovers_an_offset_and_the_horizon_beats_consecutive_readings():
    res = yaw_slice(60, seed=1, K=K, b=B, tilt_deg=10)
    start = B + [0.0, 0.0, 3.0]
    fit = link_fit(_pairs(res), K, start, ["b_z"])
    value, sd = fit.estimated["b_z"]
    assert sd < 0.5 and abs(value - B[2]) <= 3 * sd
    assert fit.rms < 0.5 * fit.rms_still     # the gyro explains the rotation
    # the derivative between consecutive readings divides the noise by 10 ms
    consecutive = link_fit(_pairs(res, 0.0), K, start, ["b_z"]).estimated["b_z"][1]
    assert consecutive > 10 * sd


def test_link_does_not_see_the_offset_along_the_only_rotation_axis():
    Kd = np.diag(np.diag(K))
    res = yaw_slice(60, seed=1, K=Kd, b=B, tilt_deg=0)      # yaw only: ω along body z
    fit = link_fit(_pairs(res), Kd, B + [0.0, 0.0, 3.0], ["b_x", "b_z"])
    assert fit.estimated["b_x"][1] < TOL
    assert not fit.estimated["b_z"][1] < 100 * TOL


def _diagnose(res, cal):
    track = res if isinstance(res, Track) else res.track
    return streamcal.diagnose(track, calibration=cal, candidates=[], ladder=False)


def _soft_iron_cal(entry=None, delta=0.0, b_delta=0.0):
    """A hard+soft-iron calibration of the true K, B with K[entry] off by ``delta`` (µT) and
    every offset off by ``b_delta``."""
    Kc = K.copy()
    if entry is not None:
        Kc[entry] += delta
    return Calibration(K=Kc, b=B + b_delta, model=("hard_iron", "soft_iron"))


@pytest.mark.slow
def test_gyro_pins_a_wrong_held_K_zz_and_the_offset_follows():
    """A yaw-turning slice (±25° tilt) leaves K_zz to trade against b_z on the sphere: K_zz is
    held at the calibration's wrong value (+1 µT) and b_z bends by ≈ 1 µT to match it."""
    res = yaw_slice(120, seed=2, K=K, b=B, tilt_deg=25, noise_uT=0.15)
    d = _diagnose(res, _soft_iron_cal((2, 2), 1.0))
    out = d.to_dict()
    json.dumps(out, allow_nan=False, default=lambda v: None)
    assert out["gyro_link"]["used"], out["gyro_link"]["reason"]
    pinned = out["gyro_pinned"]["K_zz"]
    assert pinned["held_value"] == pytest.approx(47.5)
    assert pinned["sigma"] <= out["tolerance"]
    assert abs(pinned["value"] - K[2, 2]) <= 3 * pinned["sigma"]
    assert "K_zz" not in out["held"]
    assert abs(d.calibration.K[2, 2] - K[2, 2]) < 1.0 / 3
    assert abs(d.calibration.b[2] - B[2]) < 1.0 / 3
    assert out["gyro_link"]["rms_heldout_pinned"] < out["gyro_link"]["rms_heldout_held"]
    text = held_text(d)
    assert "pinned by the gyro link" in text and "K_zz" in text.split("pinned by the gyro")[1]


@pytest.mark.slow
def test_not_pinned_when_the_rotation_does_not_determine_it():
    """Yaw ±20° with no tilt: b_y is held by the sphere, and the link sees it only through
    the yaw, where it trades against the gyro's z gain: σ above the tolerance, held."""
    res = yaw_slice(120, seed=1, K=K, b=B, tilt_deg=0, yaw_deg=20)
    d = _diagnose(res, Calibration(K=K.copy(), b=B + 2.0, model=("hard_iron",)))
    link = d.to_dict()["gyro_link"]
    assert "b_y" in d.held.parameters and not d.held.gyro_pinned and not link["used"]
    assert "does not determine" in link["reason"]
    assert link["estimates"]["b_y"]["sigma_predicted"] > d.held.tolerance
    # the same track without gyro columns: held alike, the link not tried
    bare = Track({c: v for c, v in res.track.columns.items() if c not in ("gx", "gy", "gz")},
                 res.track.metadata)
    d0 = _diagnose(bare, Calibration(K=K.copy(), b=B + 2.0, model=("hard_iron",)))
    assert d0.held.parameters == d.held.parameters
    assert d0.held.gyro_link["reason"].startswith("no gyro columns")


@pytest.mark.slow
def test_noisy_gyro_is_not_used():
    res = yaw_slice(120, seed=2, K=K, b=B, tilt_deg=25, noise_uT=0.15, gyro_noise=0.5)
    d = _diagnose(res, _soft_iron_cal((2, 2), 1.0))
    assert not d.held.gyro_pinned and not d.held.gyro_link["used"]
    assert "K_zz" in d.held.parameters


@pytest.mark.slow
def test_gyro_pins_a_wrong_held_offset_within_its_sigma():
    """Hovering (yaw ±30°, tilt ±15°, 300 s, σ 0.15 µT), calibration 2 µT off on every offset:
    the sphere re-estimates b_z but holds b_x and b_y; the link determines b_x."""
    res = yaw_slice(300, seed=1, K=K, b=B, tilt_deg=15, yaw_deg=30, noise_uT=0.15)
    d = _diagnose(res, _soft_iron_cal(b_delta=2.0))
    assert d.held.gyro_link["used"], d.held.gyro_link["reason"]
    pinned = d.held.gyro_pinned["b_x"]
    assert pinned["held_value"] == pytest.approx(B[0] + 2.0)
    assert pinned["sigma"] <= d.held.tolerance
    assert abs(pinned["value"] - B[0]) <= 3 * pinned["sigma"]
    assert abs(d.calibration.b[0] - B[0]) <= 3 * pinned["sigma"]
    assert "b_x" not in d.held.parameters
    # the guard passed (b_x does not lean on b_y), and it says b_y is held at a wrong value
    guard = d.held.gyro_link["guard"]
    assert guard["passed"] and abs(guard["shift"]["b_x"]) < pinned["sigma"]
    check = guard["held_check"]["b_y"]
    assert check["held_value"] == pytest.approx(B[1] + 2.0)
    assert check["z"] > 3 and abs(check["link_value"] - B[1]) <= 3 * check["link_sigma"]
    assert "b_y" in held_text(d).split("pinned by the gyro")[1]


@pytest.mark.slow
def test_not_pinned_when_the_gyro_value_leans_on_a_wrong_held_offset():
    """Hovering (yaw ±30°, tilt ±15°, 120 s, σ 0.4 µT), every offset 2 µT off: the sphere
    holds K_yz, K_zz, b_x, b_y; the link determines K_yz only with b_x, b_y held, and there it
    pinned the value that fits the wrong offsets (1.78 ± 0.18 against 0.6) before the guard."""
    res = yaw_slice(120, seed=1, K=K, b=B, tilt_deg=15, yaw_deg=30, noise_uT=0.4)
    d = _diagnose(res, _soft_iron_cal(b_delta=2.0))
    link = d.held.gyro_link
    assert link["candidates"] == ("K_yz",)
    assert not link["used"] and not d.held.gyro_pinned and "K_yz" in d.held.parameters
    assert d.calibration.K[1, 2] == pytest.approx(K[1, 2])     # held at the given value
    guard = link["guard"]
    assert not guard["passed"] and guard["p_value"] < P_GUARD
    assert abs(guard["shift"]["K_yz"]) > link["estimates"]["K_yz"]["sigma"]
    # what the conditional fit would have pinned is off by more than 3 of its σ: the guard
    # is what keeps it out; with every held parameter free the link's K_yz is within 3 σ
    cond = link["estimates"]["K_yz"]
    assert abs(cond["value"] - K[1, 2]) > 3 * cond["sigma"]
    value, sd = guard["unconditional"]["K_yz"]
    assert abs(value - K[1, 2]) <= 3 * sd
    for i, name in ((0, "b_x"), (1, "b_y")):
        c = guard["held_check"][name]
        assert c["held_value"] == pytest.approx(B[i] + 2.0)
        assert abs(c["link_value"] - B[i]) <= 3 * c["link_sigma"]
    assert "b_y held at" in link["reason"] and "K_yz" in link["reason"]


@pytest.mark.slow
def test_the_guard_lets_the_same_pin_through_when_the_held_offsets_are_right():
    """The same slice, offsets right and K_yz held 1.2 µT off: K_yz is pinned near the truth."""
    res = yaw_slice(120, seed=1, K=K, b=B, tilt_deg=15, yaw_deg=30, noise_uT=0.4)
    d = _diagnose(res, _soft_iron_cal((1, 2), 1.2))
    assert d.held.gyro_link["used"], d.held.gyro_link["reason"]
    assert d.held.gyro_link["guard"]["passed"] and d.held.gyro_link["guard"]["p_value"] > P_GUARD
    pinned = d.held.gyro_pinned["K_yz"]
    assert pinned["held_value"] == pytest.approx(K[1, 2] + 1.2)
    assert abs(pinned["value"] - K[1, 2]) <= 3 * pinned["sigma"]
    assert {"b_x", "b_y"} <= set(d.held.parameters)


def test_guard_shift_is_the_conditional_move_of_a_gaussian():
    """With the sandwich equal to H⁻¹ (independent pairs), holding h at h₀ moves p by
    Σ_ph Σ_hh⁻¹ (h₀ − ĥ) (the conditional mean of a Gaussian); the guard's shift is minus that
    and its χ² that move over its own variance Σ_ph² / Σ_hh."""
    from streamcal.diagnosis.held.gyro_guard import MATERIAL, held_check
    from streamcal.fitting.gyro_link import LinkFit

    rng = np.random.default_rng(3)
    A = rng.standard_normal((3, 3))
    H = A @ A.T + 0.5 * np.eye(3)       # (p, h, gyro-like nuisance)
    S = np.linalg.inv(H)
    est = {"K_yz": (0.4, float(np.sqrt(S[0, 0]))), "b_y": (-6.8, float(np.sqrt(S[1, 1])))}
    fit = LinkFit(K=np.eye(3), b=np.zeros(3), estimated=est, gyro_bias=np.zeros(3),
                  gyro_gain=np.zeros(3), rms=1.0, rms_still=2.0, sigma=1.0, tau=1.0, n_pairs=100,
                  horizon_s=1.0, bread=H, meat=H)
    sd_cond = 1 / np.sqrt(H[0, 0])
    for h0, right in ((-6.8 + 0.1 * np.sqrt(S[1, 1]), True),
                      (-6.8 + 5 * np.sqrt(S[1, 1]), False)):
        out = held_check(fit, ["K_yz", "b_y"], ["K_yz"], {"K_yz": 0.6, "b_y": h0},
                         {"K_yz": sd_cond})
        move = S[0, 1] / S[1, 1] * (h0 - est["b_y"][0])
        assert out["shift"]["K_yz"] == pytest.approx(-move, rel=1e-9)
        assert out["chi2"] == pytest.approx(move ** 2 / (S[0, 1] ** 2 / S[1, 1]), rel=1e-9)
        assert out["held_check"]["b_y"]["z"] == pytest.approx((h0 + 6.8) / np.sqrt(S[1, 1]))
        assert out["passed"] == (not (out["p_value"] < 0.003 and abs(move) > MATERIAL * sd_cond))
        assert out["passed"] == right
