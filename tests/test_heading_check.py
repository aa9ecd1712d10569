"""The heading a refinement gives against the logged attitude (streamcal.fitting.heading_check):
a turn of the field's direction that the magnitude cannot see is seen, said in the summary, and
the diagnosis and the pasted `fit --cal` report the same numbers."""
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.fitting.attitude_reference import fit_attitude_reference
from streamcal.fitting.heading_check import WORSE_DEG, heading_check
from streamcal.sim.flight import simulated_log

S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])


def _turned(cal, deg):
    """``cal`` with its body frame turned by ``deg`` about the vertical: the same magnitudes."""
    q = np.asarray((cal.extra or {}).get("frame_rotation_Q", np.eye(3)), float)
    turn = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    return cal.replace(extra={**dict(cal.extra or {}), "frame_rotation_Q": (q @ turn).tolist()})


def test_a_turn_the_magnitude_cannot_see_is_seen():
    track, _ = simulated_log("flight", duration_s=60, S=S_TRUE, b_body=B_TRUE, seed=3)
    good = fit_attitude_reference(track)
    same = heading_check(track, good, good)
    assert same["rms_after"] == same["rms_before"] and not same["worse"]
    turned = _turned(good, 4.0)
    cov = track.covariates_at_mag()
    assert np.allclose(np.linalg.norm(turned.apply(track.mag, cov), axis=1),
                       np.linalg.norm(good.apply(track.mag, cov), axis=1))
    check = heading_check(track, good, turned)
    assert check["worse"] and check["rms_after"] > check["rms_before"] + 2.5
    small = heading_check(track, good, _turned(good, WORSE_DEG / 3))
    assert not small["worse"]
    assert "0.5°" in check["rule"]


def test_no_attitude_says_why():
    track, _ = simulated_log("flight", duration_s=20, S=S_TRUE, b_body=B_TRUE)
    cal = fit_attitude_reference(track)
    track.metadata.pop("gps_lat_deg", None)
    track.metadata.pop("gps_lon_deg", None)
    out = heading_check(track, cal, cal)
    assert set(out) == {"reason"} and out["reason"]


def _run(*argv):
    run = subprocess.run([sys.executable, "-m", "streamcal", *argv], capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    return run


def test_diagnosis_and_pasted_refinement_report_the_same_heading(tmp_path):
    gain = np.array([0.6, -0.4, 0.3])
    track, _ = simulated_log("flight", duration_s=120, S=S_TRUE, b_body=B_TRUE,
                             current_gain=gain, seed=4)
    path = tmp_path / "flight.csv"
    track.write(path)
    cal = fit_attitude_reference(track, channels=())
    cal.save(tmp_path / "cal.json")
    d = json.loads(_run("diagnose", str(path), "--cal", str(tmp_path / "cal.json"),
                        "--json").stdout)
    assert d["next_step"] and "aux_interference" in d["next_step"]
    check = d["heading_check"]
    assert check["n"] > 0 and check["rms_after"] <= check["rms_before"] and not check["worse"]
    assert f"{check['rms_before']:.2f}° to {check['rms_after']:.2f}°" in d["summary"]
    argv = [a for a in d["next_step"][1:] if a != "refined.json"]
    argv[argv.index("-o")] = "--json"
    fitted = json.loads(_run(*argv).stdout)
    assert fitted["heading_check"] == check
    assert abs(fitted["rms"] - d["ladder"][-1]["rms"]) <= 0.01 * d["ladder"][-1]["rms"]


def test_a_worse_refinement_is_said_in_the_summary_and_by_fit(tmp_path, monkeypatch):
    from streamcal.diagnosis import advice

    track, _ = simulated_log("flight", duration_s=60, S=S_TRUE, b_body=B_TRUE, seed=3)
    good = fit_attitude_reference(track)
    check = heading_check(track, good, _turned(good, 4.0))

    class D:
        heading_check = check
        next_step = ["streamcal", "fit", "flight.bin", "--cal", "log", "--add", "x"]
    words = " ".join(advice.heading_sentences(D))
    assert words.startswith("Careful") and f"{check['rms_after']:.2f}°" in words
    assert "streamcal fit flight.bin --attitude" in words


def test_real_copter_refinement_keeps_the_heading_with_the_attitude(flight_dir, tmp_path):
    """The 2014 copter against the calibration in force: refined on the magnitude alone the
    compass points worse against the logged attitude (and the summary would say so); fitted
    against the attitude too, as `fit --cal` and the diagnosis now do, the ladder's effects
    lower the field error fivefold, the pasted next step gives what the ladder promised, the
    heading does not turn, and the firmware's own formula points as streamcal does."""
    from streamcal.diagnosis.against import refine
    from streamcal.inputs import autopilot_calibration, read_recording

    log = str(flight_dir / "ardupilot_erle_15-12-2014_16.BIN")
    track = read_recording(log)
    given = autopilot_calibration(track)
    magnitude = heading_check(track, given, refine(track, given, [], attitude=False))
    assert magnitude["worse"] and magnitude["rms_after"] > magnitude["rms_before"]
    d = json.loads(_run("diagnose", log, "--cal", "log", "--json").stdout)
    used = d["held_attitude_reference"]
    assert used["samples"] == magnitude["n"] and "steered by the compass" in used["caveat"]
    assert d["next_step"] and d["ladder"][-1]["rms"] < 0.2 * d["ladder"][0]["rms"]
    argv = [a if a != "refined.json" else str(tmp_path / "r.json") for a in d["next_step"][1:]]
    run = _run(*argv)
    assert "warning" not in run.stderr and "caveat" in run.stdout
    saved = json.loads((tmp_path / "r.json").read_text())
    check = saved["heading_check"]
    assert not check["worse"] and check["rms_after"] < check["rms_before"]
    assert saved["attitude_reference_used"] == used
    assert check == d["heading_check"]
    assert saved["rms"] == pytest.approx(d["ladder"][-1]["rms"], rel=1e-4)   # the promise
    # the temperature term it adds has no ArduPilot parameter: the firmware's formula points
    # less well than streamcal's own correction, but better than the calibration in force
    out = json.loads(_run("check", str(tmp_path / "r.json"), log, "--json").stdout)
    assert out["after"]["ardupilot"]["heading_rms_deg"] < out["before"]["ardupilot"][
        "heading_rms_deg"]
    # a refinement the firmware can hold whole points as streamcal does
    _run("fit", log, "--cal", "log", "-o", str(tmp_path / "r0.json"))
    out = json.loads(_run("check", str(tmp_path / "r0.json"), log, "--json").stdout)
    assert out["after"]["ardupilot"]["heading_rms_deg"] == pytest.approx(
        out["after"]["streamcal"]["heading_rms_deg"], abs=2e-3)
