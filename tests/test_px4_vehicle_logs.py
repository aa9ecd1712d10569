"""PX4 logs of the layouts streamcal has no real log of (:mod:`tests._px4_vehicle_logs`): three
``sensor_mag`` instances as PX4 1.9 drivers published them (already offset and scaled by
CAL_MAGn) and as 1.14 publishes them (the raw reading), each read back to the sensor's reading
and rebuilt by its own CAL_MAGn into the true body field."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.diagnosis.compass_consistency import calibrated_field
from streamcal.inputs import autopilot_calibration, read_compasses

from ._px4_vehicle_logs import write_px4_log
from ._vehicle_logs import soft_iron

OFFSETS = [np.array([0.1, -0.05, 0.2]), np.array([-0.2, 0.1, 0.05]), np.array([0.05, 0.3, -0.1])]


@pytest.mark.parametrize("version", ["1.9", "1.14", "1.14-vm"])
def test_three_magnetometers_each_with_its_cal_magn(version, tmp_path, capsys):
    """Each sensor_mag instance is the sensor's reading r (G × 100 = µT) — a 1.9 driver's
    ``(r − o) · scale`` undone, not taken for r (which put CAL_MAGn's offsets in twice: 0.25 G,
    half the field, off) — and CAL_MAGn of its device id rebuilds the body field; a log of
    vehicle_magnetometer only (PX4's corrected field, one instance per compass) the same, its
    S (r − o) undone."""
    A = [np.diag(np.diag(soft_iron(k))) if version == "1.9" else soft_iron(k) for k in range(3)]
    path = tmp_path / f"px4_{version}.ulg"
    truth = write_px4_log(path, version, A, OFFSETS, seconds=30.0)
    tracks = read_compasses(path)
    assert [t.metadata["mag_cal_params"] for t in tracks] == ["CAL_MAG0_", "CAL_MAG1_",
                                                               "CAL_MAG2_"]
    for k, track in enumerate(tracks):
        np.testing.assert_allclose(track.mag / 100.0, truth["raw"][k], atol=2e-6)
        _, field = calibrated_field(track, autopilot_calibration(track))
        np.testing.assert_allclose(field / 100.0, truth["e"], atol=2e-6)
        assert ("mag_driver_calibration_undone" in track.metadata) == (version == "1.9")
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) in (0, 1)
    pairs = json.loads(capsys.readouterr().out)["consistency"]
    autopilot = [p for p in pairs if p["calibration"] == "autopilot"]
    assert len(autopilot) == 3
    assert all(p["angle_deg_p95"] < 0.01 and p["fraction_inconsistent"] == 0 for p in autopilot)


def test_throttle_from_the_thrust_setpoint_of_px4_1_14(tmp_path):
    """PX4 1.14 logs no actuator_controls_0: the throttle is the length of
    vehicle_thrust_setpoint.xyz (0..1)."""
    path = tmp_path / "px4_1.14.ulg"
    truth = write_px4_log(path, "1.14", [np.eye(3)], OFFSETS[:1], seconds=10.0)
    track = read_compasses(path)[0]
    assert track.metadata["throttle_source"] == "|vehicle_thrust_setpoint.xyz| (0..1)"
    got = np.asarray(track.columns["throttle"], float)
    np.testing.assert_allclose(got[np.isfinite(got)], np.hypot(0.02, truth["throttle"]),
                               rtol=1e-6)


def test_the_default_magnetometer_of_px4_1_9_is_cal_mag_prime(tmp_path):
    """PX4 up to 1.11 has no CAL_MAGn_PRIO: the magnetometer it uses first is CAL_MAG_PRIME's
    device id (here instance 1's), not instance 0; with CAL_MAGn_PRIO (1.14) the priority
    decides."""
    A = [np.eye(3)] * 2
    old = tmp_path / "px4_1.9.ulg"
    write_px4_log(old, "1.9", A, OFFSETS[:2], seconds=5.0, prime=1)
    assert read_compasses(old)[0].metadata["compass_default"] == "1"
    new = tmp_path / "px4_1.14.ulg"
    write_px4_log(new, "1.14", A, OFFSETS[:2], seconds=5.0, prime=1, prio=(75, 50))
    assert read_compasses(new)[0].metadata["compass_default"] == "0"
