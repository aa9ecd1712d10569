"""A PX4 compass mounted rotated (CAL_MAG0_ROT ≠ 0, or SENS_BOARD_ROT for an internal one):
``sensor_mag`` is logged in the sensor's own frame and PX4 turns it into the body frame after its
calibration. Every heading figure against the logged attitude — the attitude line of diagnose,
``fit --cal autopilot``'s heading check, ``streamcal check`` with each firmware's formula and
streamcal's own correction — must be the one computed here from the truth: PX4's formula
``R S (r + p·comp − o)`` with the known mounting matrix, set against the World Magnetic Model
turned by the logged attitude. Self-made ULogs (tests/_selfmade_logs.py) of two simulated flights
(:func:`streamcal.sim.flight.simulated_log`) with a battery-current motor field that the
calibration in force does not compensate."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.calibration import Calibration, canonical_form
from streamcal.cli import main
from streamcal.export import export
from streamcal.export.motor_check import flight_check
from streamcal.fitting.attitude_reference import (attitude_data, calibration_in_force,
                                                  log_attitude_reference)
from streamcal.inputs import px4_rotation, read_recording
from streamcal.inputs.mount_rotations import by_name
from streamcal.sim.flight import simulated_log

from ._selfmade_logs import px4_flight_ulog_bytes, px4_matrix_offsets, px4_mounted_params

S_BODY = np.array([[1.05, 0.03, -0.02], [0.03, 0.96, 0.01], [-0.02, 0.01, 1.02]])
B_BODY = np.array([15.0, -9.0, 22.0])
GAIN = np.array([0.25, -0.15, 0.3])          # µT/A in the body frame: 2..16 µT over 5..35 A
MOUNT = by_name("ROLL_180_YAW_90")           # PX4 and ArduPilot number 10


def _flight(path, seed: int, internal: bool = False):
    """A flight of the vehicle as PX4 logs it, the calibration in force exact but for the motor
    field (CAL_MAG_COMP_TYP 0); the mounting in CAL_MAG0_ROT, or SENS_BOARD_ROT when
    ``internal`` (CAL_MAG0_ROT −1). (path, the CAL_MAG0_* written)."""
    track, _ = simulated_log("flight", duration_s=240, seed=seed, S=S_BODY, b_body=B_BODY,
                             mount=MOUNT.matrix, current_gain=GAIN)
    params = px4_mounted_params(MOUNT.matrix, MOUNT.px4, S_BODY, B_BODY)
    if internal:
        params.update(CAL_MAG0_ROT=-1, SENS_BOARD_ROT=MOUNT.px4)
    path.write_bytes(px4_flight_ulog_bytes(track, params))
    return path, params


def _px4_formula(params: dict, m_uT: np.ndarray, amps: np.ndarray) -> np.ndarray:
    """PX4's correction of readings (M,3) µT into the body frame, µT, with the known mounting:
    ``R S (r + 0.001 I comp − o)`` in gauss (CAL_MAG_COMP_TYP 2 or 0)."""
    S, o = px4_matrix_offsets(params)
    r = m_uT / 100.0
    if params.get("CAL_MAG_COMP_TYP", 0) == 2:
        r = r + 0.001 * amps[:, None] * np.array([params[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])
    return 100.0 * ((r - o) @ S.T) @ MOUNT.matrix.T


def _heading_rms(track, field_of) -> float:
    """rms (degrees) of the angle between the horizontal parts of the body-frame field that
    ``field_of(m, amps)`` gives, turned to NED by the logged attitude, and the model's."""
    data, why = attitude_data(track)
    assert data is not None, why
    f = Rotation.from_quat(data.q[:, [1, 2, 3, 0]]).apply(
        field_of(data.m, data.cov["battery_current_a"]))
    d = np.arctan2(f[:, 1], f[:, 0]) - np.arctan2(data.b_ned[1], data.b_ned[0])
    return float(np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * d)) ** 2))))


def _exported_px4(cal: Calibration) -> dict:
    text = export(cal, "px4")[0]
    return {line.split("\t")[2]: float(line.split("\t")[3])
            for line in text.splitlines() if line.startswith("1\t")}


def _true_calibration() -> Calibration:
    """The truth as a streamcal calibration of the sensor-frame readings:
    ``m = |F| Mᵀ S_body u + Mᵀ b_body + Mᵀ g I``, ``u`` the body-frame direction."""
    F = 48.0
    K, Q = canonical_form(F * MOUNT.matrix.T @ S_BODY)
    return Calibration(K=K, b=MOUNT.matrix.T @ B_BODY,
                       model=("hard_iron", "soft_iron", "aux_interference"),
                       effects={"aux_interference": {"channels": {"battery_current_a": {
                           "a0": 0.0, "g": [float(v) for v in MOUNT.matrix.T @ GAIN]}}}},
                       field=F, unit="uT", extra={"frame_rotation_Q": Q.tolist()})


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """(flight 1, flight 2, the CAL_MAG0_* in force, new.json refined on flight 1)."""
    d = tmp_path_factory.mktemp("px4rot")
    (one, params), (two, _) = _flight(d / "one.ulg", 0), _flight(d / "two.ulg", 1)
    new = d / "new.json"
    assert main(["fit", str(one), "--cal", "autopilot", "--add",
                 "aux_interference=battery_current_a", "-o", str(new)]) == 0
    return one, two, params, new


def test_the_reader_says_sensor_mag_and_the_rotation_is_found(flights):
    one, _, _, _ = flights
    meta = read_recording(one).metadata
    assert meta["mag_calibrated_by_px4"].startswith("no")
    assert px4_rotation(meta) == pytest.approx(MOUNT.matrix)
    assert px4_rotation(dict(meta, mag_calibrated_by_px4="yes")) is None
    ardupilot = {"input_format": "ardupilot-dataflash", "param.COMPASS_ORIENT": "10"}
    assert px4_rotation(ardupilot) is None      # ArduPilot logs the field already rotated


@pytest.mark.parametrize("internal", [False, True], ids=["CAL_MAG0_ROT", "SENS_BOARD_ROT"])
def test_attitude_line_of_the_calibration_in_force_is_the_truths(tmp_path, internal):
    path, params = _flight(tmp_path / "f.ulg", 2, internal)
    track = read_recording(path)
    truth = _heading_rms(track, lambda m, amps: _px4_formula(params, m, amps))
    assert truth > 5.0            # the uncompensated motor field turns the heading
    ref = log_attitude_reference(track)
    assert ref["attitude_reference"]["heading_error_deg"]["rms_before"] == pytest.approx(
        truth, rel=0.02)
    # an internal compass is turned by the board rotation (CAL_MAG0_ROT −1): already right
    param = "SENS_BOARD_ROT" if internal else "CAL_MAG0_ROT"
    assert ref["orientation"]["configured"] == {"param": param, "value": MOUNT.px4}
    assert ref["orientation"]["set"] == {"param": param, "value": MOUNT.px4}


def test_fit_heading_check_of_a_refinement_is_the_truths(flights):
    one, _, params, new = flights
    track = read_recording(one)
    check = json.loads(new.read_text())["heading_check"]
    refined = Calibration.load(new)
    after = _heading_rms(track, lambda m, amps: _px4_formula(_exported_px4(refined), m, amps))
    assert check["rms_before"] == pytest.approx(
        _heading_rms(track, lambda m, amps: _px4_formula(params, m, amps)), rel=0.02)
    assert check["rms_after"] == pytest.approx(after, rel=0.05, abs=0.1)
    assert check["rms_after"] < check["rms_before"] / 3 and not check["worse"]


def test_check_figures_are_the_truths(flights, tmp_path, capsys):
    _, two, params, new = flights
    track = read_recording(two)
    before = _heading_rms(track, lambda m, amps: _px4_formula(params, m, amps))
    refined = Calibration.load(new)
    after = _heading_rms(track, lambda m, amps: _px4_formula(_exported_px4(refined), m, amps))
    capsys.readouterr()
    assert main(["check", str(new), str(two), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for fw in ("ardupilot", "px4"):
        assert out["before"][fw]["heading_rms_deg"] == pytest.approx(before, rel=0.02)
        assert out["after"][fw]["heading_rms_deg"] == pytest.approx(after, rel=0.05, abs=0.1)
    assert out["after"]["streamcal"]["heading_rms_deg"] == pytest.approx(after, rel=0.05, abs=0.1)
    assert out["compare"]["px4"]["better"]

    true_cal = tmp_path / "true.json"
    _true_calibration().save(true_cal)
    true_params = px4_mounted_params(MOUNT.matrix, MOUNT.px4, S_BODY, B_BODY,
                                     comp_g_per_ka=-10.0 * MOUNT.matrix.T @ GAIN)
    noise = _heading_rms(track, lambda m, amps: _px4_formula(true_params, m, amps))
    assert noise < 1.0            # 0.3 µT per axis against a ~21 µT horizontal field
    assert main(["check", str(true_cal), str(two), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for which in ("ardupilot", "px4", "streamcal"):
        assert out["after"][which]["heading_rms_deg"] == pytest.approx(noise, rel=0.05, abs=0.05)


def test_a_calibration_without_frame_is_turned_like_the_readings(flights):
    """A calibration with no frame_rotation_Q (a sphere fit of the readings) is in the frame of
    the readings: PX4 turns it by CAL_MAG0_ROT, and so does streamcal's own correction."""
    _, two, _, _ = flights
    track = read_recording(two)
    sensor_frame = Calibration(K=48.0 * np.eye(3), b=MOUNT.matrix.T @ B_BODY,
                               model=("hard_iron", "soft_iron", "aux_interference"),
                               effects=_true_calibration().effects, field=48.0, unit="uT")
    out = flight_check(track, sensor_frame, calibration_in_force(track))["after"]
    assert out["streamcal"]["heading_rms_deg"] == pytest.approx(out["px4"]["heading_rms_deg"],
                                                                abs=0.01)
    assert out["px4"]["heading_rms_deg"] < 5.0     # the iron left out; turned wrongly: ~100°


def test_the_refinement_fitted_against_the_attitude_comes_near_the_truth(flights):
    """The refinement of the rotated compass is fitted against the attitude too: its heading
    comes within 0.5° of the true calibration's; so does the magnitude alone now that it
    re-estimates the field strength the calibration in force holds (it stayed over 1.5° above
    while the motor field set that strength, RESULTS §7.7, §8.1)."""
    from streamcal.diagnosis.against import refine
    from streamcal.fitting.heading_check import heading_check

    one, _, _, new = flights
    saved = json.loads(new.read_text())
    assert saved["attitude_reference_used"]["samples"] == saved["heading_check"]["n"]
    track = read_recording(one)
    true_params = px4_mounted_params(MOUNT.matrix, MOUNT.px4, S_BODY, B_BODY,
                                     comp_g_per_ka=-10.0 * MOUNT.matrix.T @ GAIN)
    noise = _heading_rms(track, lambda m, amps: _px4_formula(true_params, m, amps))
    assert saved["heading_check"]["rms_after"] < noise + 0.5
    in_force = calibration_in_force(track)
    magnitude = refine(track.keep_aux(["battery_current_a"]), in_force, ["aux_interference"],
                       attitude=False)
    assert "radius" not in magnitude.extra["held"]
    assert heading_check(track, in_force, magnitude)["rms_after"] < noise + 0.5
