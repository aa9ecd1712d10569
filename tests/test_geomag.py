"""The local field as a physical reference: WMM2025 values, the comparison in ``diagnose``,
``report`` and the live page."""
from __future__ import annotations

import datetime
import json
import math
import subprocess
import sys
import time

import pytest

from streamcal.errors import InputError
from streamcal.geomag import compare, dip_deg, wmm_field
from streamcal.sim.scenario import simulate
from tests.test_live_page import REPO, sse_events, start_daemon

# NOAA's published WMM2025 test values (WMM2025_TestValues): decimal year 2025.0, height 0 km,
# lat, lon → X, Y, Z (nT, printed to 0.1 nT) and declination (°, printed to 0.01°).
NOAA_2025 = [
    (80.0, 0.0, 6521.6, 145.9, 54791.5, 1.28),
    (0.0, 120.0, 39677.8, -109.6, -10580.2, -0.16),
    (-80.0, 240.0, 6117.5, 15751.9, -52022.5, 68.78),
]
# WMM2025 at 43° N, 21° E on 2025-07-01: 47.97 µT, inclination 60.26° (the simulator's default
# Earth field is 48 µT at a dip of 60°).
SIM_PLACE = ["--lat", "43", "--lon", "21", "--date", "2025-07-01"]


@pytest.mark.parametrize("lat, lon, x, y, z, dec", NOAA_2025)
def test_wmm_matches_noaa_test_values(lat, lon, x, y, z, dec):
    r = wmm_field(lat, lon, 0.0, datetime.date(2025, 1, 1))
    assert r["source"] == "WMM2025" and r["decimal_year"] == 2025.0
    f = math.sqrt(x * x + y * y + z * z) / 1000.0
    incl = math.degrees(math.atan2(z, math.hypot(x, y)))
    assert abs(r["intensity_uT"] - f) < 2e-4                 # 0.2 nT: rounding of X, Y, Z
    assert abs(r["inclination_deg"] - incl) < 2e-3
    assert abs(r["declination_deg"] - dec) < 0.006           # printed to 0.01°


def test_bad_place_and_date_are_clear():
    with pytest.raises(InputError, match="--lat"):
        wmm_field(91, 0)
    with pytest.raises(InputError, match="WMM2025 covers 2025 to 2030"):
        wmm_field(43, 21, 0, datetime.date(2031, 1, 1))


def test_counts_track_gets_a_scale_and_dip_hint():
    ref = wmm_field(43, 21, 0, datetime.date(2025, 7, 1))
    out = compare(ref, 320.0, "counts", fitted_dip_deg=ref["inclination_deg"] + 5.0)
    assert out["uT_per_count"] == pytest.approx(ref["intensity_uT"] / 320.0, rel=1e-5)
    assert any("µT per count" in n for n in out["notes"])
    assert out["dip_difference_deg"] == pytest.approx(5.0, abs=1e-3)
    assert any(n.startswith("hint:") and "misalignment" in n for n in out["notes"])
    assert compare(None, 48.0, "uT") == {"source": None,
                                         "reason": "no location given (--lat/--lon)"}


def test_dip_of_a_known_geometry():
    down = [[0.0, 0.0, 1.0]] * 3
    field = [[math.cos(math.radians(60)), 0.0, math.sin(math.radians(60))]] * 3
    med, spread = dip_deg(field, down)
    assert med == pytest.approx(60.0) and spread == pytest.approx(0.0, abs=1e-9)


@pytest.fixture(scope="module")
def sim_track(tmp_path_factory):
    path = tmp_path_factory.mktemp("geomag") / "sim.csv"
    simulate(120, seed=3, motor=False, field_uT=48.0, dip_deg=60.0).track.write(path)
    return path


def _diagnose(*args):
    out = subprocess.run([sys.executable, "-m", "streamcal", "diagnose", *map(str, args)],
                         capture_output=True, text=True, cwd=REPO, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.mark.slow
def test_simulated_48uT_60deg_matches_a_place_with_those_numbers(sim_track):
    ref = json.loads(_diagnose(sim_track, "--json", *SIM_PLACE))["reference_field"]
    assert ref["source"] == "WMM2025" and ref["field_unit"] == "uT"
    assert abs(ref["field_ratio"] - 1.0) < 0.05, ref         # the sensor's own gain is random
    assert abs(ref["dip_difference_deg"]) < 1.0, ref
    assert ref["fitted_dip_deg"] == pytest.approx(60.0, abs=1.0)
    # the same track at the equator (inclination −15°) is off by ~75° and says so
    far = json.loads(_diagnose(sim_track, "--json", "--lat", "0", "--lon", "120",
                               "--date", "2025-07-01"))["reference_field"]
    assert far["dip_difference_deg"] == pytest.approx(75.0, abs=2.0)
    assert any(n.startswith("hint:") for n in far["notes"])
    text = _diagnose(sim_track, *SIM_PLACE)
    assert "reference  WMM2025 at 43.0000°, 21.0000°" in text and "fitted dip" in text


@pytest.mark.slow
def test_no_location_says_so(sim_track):
    ref = json.loads(_diagnose(sim_track, "--json"))["reference_field"]
    assert ref == {"source": None, "reason": "no location given (--lat/--lon)"}
    assert "reference  none: no location given (--lat/--lon)" in _diagnose(sim_track)


@pytest.mark.slow
def test_report_has_the_local_field(sim_track, tmp_path):
    out = tmp_path / "r.html"
    run = subprocess.run([sys.executable, "-m", "streamcal", "report", str(sim_track), "-o",
                          str(out), *SIM_PLACE], capture_output=True, text=True, cwd=REPO,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    html = out.read_text()
    assert '<section id="reference-field">' in html and "fitted dip" in html


@pytest.mark.slow
def test_live_page_compares_with_the_local_field(tmp_path):
    proc, url = start_daemon(tmp_path, *SIM_PLACE, speed="4", seconds="60")
    try:
        deadline = time.monotonic() + 40
        ref = None
        while time.monotonic() < deadline:
            events = sse_events(url, seconds=1.5)
            if events and events[-1]["calibration"] and events[-1]["reference"]["fitted_dip_deg"]:
                ref, ring = events[-1]["reference"], events[-1]["ring"]
                break
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert ref is not None, "no calibration with a dip on the page within 40 s"
    assert ref["source"] == "WMM2025" and ref["intensity_uT"] == pytest.approx(47.97, abs=0.01)
    assert abs(ref["dip_difference_deg"]) < 3.0, ref            # block medians under hand motion
    assert abs(ref["field_ratio"] - 1.0) < 0.05, ref
    # the ring the field must lie on at the current roll and pitch, and the field on it
    print("ring:", ring)
    assert ring["source"] == "WMM2025 inclination" and ring["dip_deg"] == pytest.approx(60.26)
    assert math.hypot(*ring["down"]) == pytest.approx(1.0, abs=1e-3)
    assert ring["off_deg"] is not None and ring["off_deg"] < 5.0, ring
