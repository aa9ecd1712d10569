"""ArduPilot's compass consistency limits of each firmware (``diagnose --compass all``): 50°, 30°
and 100 mG before the January 2017 relaxation (Copter < 3.5, Plane < 3.8, Rover < 3.2), 90°,
60° and 200 mG since; the share of samples over them recomputed here from the truth the
self-made logs were written from (the corrected field each firmware logs and compares)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.diagnosis.compass_consistency import LIMITS, OLD_LIMITS, limits_for

from ._vehicle_logs import Compass, soft_iron, write_vehicle_log


@pytest.mark.parametrize("firmware, expected, why", [
    ("APM:Copter V3.4.6 (abc)", OLD_LIMITS, "Copter 3.4, before the limits were relaxed in "
                                            "Copter 3.5"),
    ("APM:Copter V3.5.0", LIMITS, "Copter 3.5: the limits since Copter 3.5"),
    ("ArduCopter V3.2.1", OLD_LIMITS, "Copter 3.2, before the limits were relaxed in Copter "
                                      "3.5; the oldest limits known, assumed: this firmware's "
                                      "own check is not established"),
    ("ArduPlane V3.7.1 (x)", OLD_LIMITS, "Plane 3.7, before the limits were relaxed in Plane 3.8"),
    ("ArduPlane V3.8.0", LIMITS, "Plane 3.8: the limits since Plane 3.8"),
    ("APM:Rover v3.1.2", OLD_LIMITS, "Rover 3.1, before the limits were relaxed in Rover 3.2"),
    ("ArduRover V4.2.3", LIMITS, "Rover 4.2: the limits since Rover 3.2"),
    ("ArduSub V3.5.4", LIMITS, "Sub 3.5: the current limits assumed"),
    (None, LIMITS, "no ArduPilot version in the log: the current limits assumed")])
def test_limits_of_each_firmware(firmware, expected, why):
    limits = limits_for(firmware)
    assert limits.values() == expected and limits.why == why


def test_limits_of_another_autopilot():
    limits = limits_for("PX4 v1.14.0", "px4-ulog")
    assert limits.values() == LIMITS and limits.why.startswith("not an ArduPilot log")


def _body_xy_angle(u, v):
    cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return np.degrees(np.abs(np.arctan2(cross, np.sum(u[:, :2] * v[:, :2], 1))))


def _share(fa, fb, limits):
    """Share of samples ``Compass::consistent`` fails under ``limits`` (fields in mG)."""
    cos = np.sum(fa * fb, 1) / np.linalg.norm(fa, axis=1) / np.linalg.norm(fb, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    xy_len = np.linalg.norm(fa[:, :2] - fb[:, :2], axis=1)
    return np.mean((angle > limits["angle_deg"]) | (_body_xy_angle(fa, fb)
                                                    > limits["xy_angle_deg"])
                   | (xy_len > 10 * limits["xy_length_uT"]))


@pytest.mark.parametrize("vehicle, limits", [("copter34", OLD_LIMITS), ("copter4", LIMITS)])
def test_share_inconsistent_under_the_logs_firmware(vehicle, limits, tmp_path, capsys):
    """The same two compasses (compass 1's COMPASS_OFS2 120 mG off in X) logged by Copter 3.4 and
    Copter 4.3: the autopilot-calibration pair's share over the limits equals the share
    recomputed from the logged (corrected) fields under that firmware's limits, and the two
    firmware's shares differ (the old limits fail far more samples)."""
    compasses = [Compass(A=soft_iron(k), b=np.array([12.0, -7.0, 20.0]) * (k + 1) / 2)
                 for k in range(2)]
    compasses[1].ofs_error = np.array([120.0, 0.0, 0.0])
    path = tmp_path / f"{vehicle}.bin"
    truth = write_vehicle_log(path, vehicle, compasses, seconds=60.0)
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) in (0, 1)
    out = json.loads(capsys.readouterr().out)
    pair = next(p for p in out["consistency"] if p["calibration"] == "autopilot")
    fa, fb = truth.logged[0], truth.logged[1]
    share = _share(fa, fb, limits)
    other = _share(fa, fb, LIMITS if limits is OLD_LIMITS else OLD_LIMITS)
    # streamcal rebuilds the corrected field from COMPASS_* (offsets rounded to 1 mG in MAG)
    assert pair["fraction_inconsistent"] == pytest.approx(share, abs=3 / len(fa))
    assert abs(share - other) > 0.05
    assert {k: out["consistency_limits"][k] for k in limits} == limits
    assert ("3.4, before" if limits is OLD_LIMITS else "4.3: the limits since") in \
        out["consistency_limits"]["why"]
    assert main(["diagnose", str(path), "--compass", "all"]) in (0, 1)
    text = capsys.readouterr().out
    deg = f"3-D angle {limits['angle_deg']:g} deg, body X-Y angle {limits['xy_angle_deg']:g} deg"
    assert f"limits: ArduPilot's consistency limits (Compass::consistent): {deg}" in text
    assert out["consistency_limits"]["why"] in text
