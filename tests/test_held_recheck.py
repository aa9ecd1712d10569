"""A parameter reported as re-estimated against a given calibration is determined by the slice
(issue #10): re-checked at the fitted point, within its plausible range, the LM status shown."""
from __future__ import annotations

import json

import numpy as np
import pytest

import streamcal
from streamcal.diagnosis.held import field_radius
from streamcal.diagnosis.held_check import SUSPICIOUS_SIGMAS, implausible_effect, plausible_range
from streamcal.fitting.damped_lm import STATUSES
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.model.nonlinear import AxisNonlinearity

from .conftest import SHARED

FLIGHT = SHARED / "data" / "real" / "flight"


@pytest.fixture(scope="module", params=["ardupilot_erle_PXFv2.0b_Rpi.BIN",
                                        "ardupilot_erle_15-12-2014_16.BIN"])
def flight(request):
    path = FLIGHT / request.param
    if not path.exists():
        pytest.skip(f"{path} not found (set STREAMCAL_SHARED)")
    track = read_recording(path)
    cal = autopilot_calibration(track)
    return cal, streamcal.diagnose(track, calibration=cal)


@pytest.mark.slow
def test_every_reestimated_parameter_is_determined_and_plausible(flight):
    cal, d = flight
    r = field_radius(cal.K)
    assert d.tolerance == pytest.approx(0.005 * r)
    assert d.estimated, "a 152 s / 1231 s flight determines at least b_z"
    for name, est in d.estimated.items():
        assert est["sigma"] <= d.tolerance, (name, est)
        lo, hi = plausible_range(name, r, cal.b)
        assert lo <= est["value"] <= hi, (name, est, (lo, hi))
        assert name not in d.held
    assert not d.suspicious   # with a calibration nothing is kept against the rule


def test_held_fit_status_and_recheck_reach_the_output(flight):
    _, d = flight
    out = json.loads(json.dumps(d.to_dict(), allow_nan=False, default=lambda v: None))
    st = out["fit_status"]
    assert st["status"] in STATUSES and st["iterations"] >= 1 and st["message"]
    for h in out["held_after_fit"]:
        assert h["parameter"] in out["held"] and h["parameter"] not in out["estimated"]
        assert h["reason"]
        # held because it failed: σ above the tolerance or out of range by > 3 σ
        lo, hi = h["range"]
        outside = max(lo - h["value"], h["value"] - hi, 0.0)
        assert h["sigma"] > out["tolerance"] or outside > SUSPICIOUS_SIGMAS * h["sigma"]
    for c in out["candidates"]:
        if "implausible" in c:
            assert not c["significant"]


@pytest.mark.slow
def test_cli_text_says_how_the_held_fit_ended(capsys):
    from streamcal.cli import main

    path = FLIGHT / "ardupilot_erle_15-12-2014_16.BIN"
    if not path.exists():
        pytest.skip(f"{path} not found")
    assert main(["diagnose", str(path), "--cal", "autopilot"]) == 0
    text = capsys.readouterr().out
    assert "held fit   " in text and " iterations" in text


def test_implausible_effect_flags_a_degenerate_cubic_gain():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(200, 3))
    u *= 25.0 / np.linalg.norm(u, axis=1, keepdims=True)
    term = AxisNonlinearity(1.0)
    assert implausible_effect([(term, np.array([1e-5, 0.0, 0.0]))], u, {}, 25.0) == ""
    why = implausible_effect([(term, np.array([0.0, 2.8e8, 0.0]))], u, {}, 25.0)
    assert why.startswith("implausible") and "field radius" in why


def test_plausible_ranges():
    b = np.array([1.0, -2.0, 3.0])
    assert plausible_range("K_xy", 40.0, b) == (-40.0, 40.0)
    assert plausible_range("K_zz", 40.0, b) == (20.0, 80.0)
    assert plausible_range("b_y", 40.0, b) == (-42.0, 38.0)
