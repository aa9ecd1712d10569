"""The attitude reference (WMM rotated by the logged attitude), the mounting-rotation table and
its detection, on a simulated vehicle with a known truth and on the real flight logs."""
import json
import subprocess
import sys

import numpy as np
import pytest

from streamcal.fitting.attitude_reference import attitude_reference, attitude_data
from streamcal.inputs.mount_rotations import by_name, mount_rotations
from streamcal.fitting.reference_fit import fit_reference
from streamcal.sim.flight import simulated_log

S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])


def test_rotation_table_follows_the_autopilots_definitions():
    # ArduPilot's rotate(): YAW_90 is x' = -y, y' = x; ROLL_180_YAW_90 is x' = y, y' = x, z' = -z
    v = np.array([1.0, 2.0, 3.0])
    assert by_name("YAW_90").matrix @ v == pytest.approx([-2.0, 1.0, 3.0])
    assert by_name("ROLL_180_YAW_90").matrix @ v == pytest.approx([2.0, 1.0, -3.0])
    assert by_name("PITCH_180").matrix @ v == pytest.approx([-1.0, 2.0, -3.0])
    table = mount_rotations()
    assert table[0].name == "NONE" and table[0].ardupilot == 0 == table[0].px4
    mats = np.array([r.matrix for r in table])
    # every entry a distinct proper rotation (the enum's duplicates merged)
    assert np.allclose(np.linalg.det(mats), 1.0)
    assert len({tuple(np.round(m, 6).ravel()) for m in mats}) == len(table)
    shared = [r for r in table if r.ardupilot is not None]
    assert all(r.ardupilot == r.px4 and r.ardupilot <= 37 for r in shared)
    assert {r.px4 for r in table if r.ardupilot is None} <= {41, 42, 43, 46, 47}


@pytest.mark.parametrize("mount", ["NONE", "YAW_90", "YAW_225", "ROLL_180", "PITCH_270"])
def test_flight_recovers_iron_offsets_and_mounting(mount):
    track, truth = simulated_log("flight", mount=by_name(mount).matrix, S=S_TRUE, b_body=B_TRUE,
                                 seed=3)
    data, why = attitude_data(track)
    assert data is not None, why
    out = attitude_reference(track)
    ref, orient = out["attitude_reference"], out["orientation"]
    assert orient["name"] == mount and orient["ardupilot"] == by_name(mount).ardupilot
    # 1200 samples, 0.3 µT noise per axis, the field turning by ~25 µT: σ(A) ~ 4e-4, σ(b) ~ 0.02 µT
    fit = fit_reference(data.m, data.expected, rotation=by_name(mount))
    assert np.abs(fit.A - S_TRUE).max() < 5e-3
    assert np.abs(fit.b - B_TRUE).max() < 0.2
    # noise 0.3 µT per axis: residual norm rms √3·0.3 = 0.52 µT
    assert ref["rms_uT_after"] < 0.6 < 5 < ref["rms_uT_before"]
    assert ref["heading_error_deg"]["rms_after"] < 1.0 < ref["heading_error_deg"]["rms_before"]
    assert orient["angle_error_deg"] < 0.2
    assert ref["undetermined"] == {}


def test_motor_current_term_is_recovered():
    gain = np.array([0.2, -0.1, 0.3])
    track, _ = simulated_log("flight", S=S_TRUE, b_body=B_TRUE, current_gain=gain, seed=5)
    data, _ = attitude_data(track)
    fit = fit_reference(data.m, data.expected, {"battery_current_a": data.cov["battery_current_a"]})
    assert np.abs(fit.g["battery_current_a"] - gain).max() < 0.01


def test_still_vehicle_holds_iron_and_does_not_guess_a_mounting():
    track, _ = simulated_log("still", duration_s=20, b_body=B_TRUE, mount=by_name("YAW_90").matrix)
    out = attitude_reference(track)
    assert out["orientation"] is None
    assert set(out["attitude_reference"]["undetermined"]) == {"A11", "A22", "A33", "A12", "A13",
                                                              "A23"}
    assert "soft iron held" in out["attitude_reference"]["note"]


def test_no_attitude_or_no_position_says_why():
    track, _ = simulated_log("flight", duration_s=20)
    meta = {k: v for k, v in track.metadata.items() if not k.startswith("gps_")}
    no_gps = type(track)(track.columns, meta)
    out = attitude_reference(no_gps)["attitude_reference"]
    assert out["rms_uT_before"] is None and "GPS" in out["reason"]
    cols = {k: v for k, v in track.columns.items() if not k.startswith("att_")}
    out = attitude_reference(type(track)(cols, track.metadata))["attitude_reference"]
    assert out["rms_uT_after"] is None and "attitude" in out["reason"]


def test_attitude_columns_are_not_auxiliary_channels():
    track, _ = simulated_log("flight", duration_s=10, current_gain=np.array([0.1, 0, 0]))
    assert track.aux_names == ["battery_current_a"]


def test_diagnose_json_carries_the_reference(tmp_path):
    track, _ = simulated_log("flight", duration_s=60, mount=by_name("YAW_90").matrix, S=S_TRUE,
                             b_body=B_TRUE)
    path = tmp_path / "flight.csv"
    track.write(path)
    run = subprocess.run([sys.executable, "-m", "streamcal", "diagnose", str(path), "--json"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    ref = out["attitude_reference"]
    assert set(ref) >= {"rms_uT_before", "rms_uT_after", "heading_error_deg", "window_s", "caveat"}
    assert set(ref["heading_error_deg"]) == {"rms_before", "rms_after", "p95_before", "p95_after"}
    assert out["orientation"]["name"] == "YAW_90" and out["orientation"]["px4"] == 2


def test_real_ardupilot_log_reference(flight_dir):
    from streamcal.inputs import autopilot_calibration, read_recording

    track = read_recording(flight_dir / "ardupilot_erle_15-12-2014_16.BIN")
    assert track.metadata["gps_date"] == "2014-12-15"          # GPS week 1823
    assert abs(float(track.metadata["gps_lat_deg"]) - 42.846) < 0.001
    out = attitude_reference(track, autopilot_calibration(track))
    ref = out["attitude_reference"]
    assert ref["reference"]["source"] == "WMM2010"
    assert ref["rms_uT_after"] < ref["rms_uT_before"]
    assert ref["heading_error_deg"]["rms_after"] < ref["heading_error_deg"]["rms_before"]
    assert out["orientation"]["name"] == "NONE"


def test_real_px4_log_reference(flight_dir):
    from streamcal.inputs import read_recording

    track = read_recording(flight_dir / "px4_pyulog_sample_px4_events.ulg")
    assert track.metadata["gps_date"] == "2024-03-18"
    data, why = attitude_data(track)
    assert data is not None, why
    # the unit quaternion of vehicle_attitude, interpolated and renormalised
    assert np.allclose(np.linalg.norm(data.q, axis=1), 1.0)
    out = attitude_reference(track)["attitude_reference"]
    assert out["rms_uT_before"] is not None and out["window_s"][1] > out["window_s"][0]


def test_fit_attitude_and_export_write_the_mounting(tmp_path):
    from streamcal.export import export
    from streamcal.export.ardupilot import apply_ardupilot
    from streamcal.fitting.attitude_reference import fit_attitude_reference

    gain = np.array([0.2, -0.1, 0.3])
    mount = by_name("YAW_90").matrix
    track, _ = simulated_log("flight", mount=mount, S=S_TRUE, b_body=B_TRUE, current_gain=gain)
    cal = fit_attitude_reference(track, channels=["battery_current_a"])
    assert cal.extra["orientation"]["name"] == "YAW_90"
    text, _ = export(cal, "ardupilot")
    params = dict(line.split(",") for line in text.splitlines() if not line.startswith("#"))
    params = {k: float(v) for k, v in params.items()}
    assert params["COMPASS_ORIENT"] == 2 and params["COMPASS_MOTCT"] == 2
    # ArduPilot's own chain: rotate the reading by COMPASS_ORIENT, then offsets, matrix, motor
    data, _ = attitude_data(track)
    f = apply_ardupilot(params, (10.0 * data.m) @ mount.T, data.cov["battery_current_a"])
    err = np.linalg.norm(f / 10.0 - data.expected, axis=1)
    assert np.median(err) < 0.6          # µT: the 0.3 µT per-axis noise
    px4 = export(cal, "px4")[0]
    assert "\tCAL_MAG0_ROT\t2\t" in px4
    # the offsets PX4 subtracts in the sensor frame: mountᵀ b_body, in gauss
    off = {ln.split("\t")[2]: float(ln.split("\t")[3]) for ln in px4.splitlines()
           if ln.startswith("1\t") and "OFF" in ln}
    assert [off[f"CAL_MAG0_{a}OFF"] for a in "XYZ"] == pytest.approx(mount.T @ B_TRUE / 100,
                                                                     abs=3e-3)


@pytest.mark.parametrize("mount", ["NONE", "ROLL_180", "YAW_90", "PITCH_90", "ROLL_90_YAW_45"])
def test_gravity_finds_the_mounting_without_attitude(mount):
    from streamcal.fitting.attitude_reference import log_attitude_reference
    from streamcal.fitting.orientation_gravity import orientation_from_gravity
    from streamcal.geomag import parse_date, wmm_field
    from streamcal.sim.flight import DATE, LAT, LON

    track, _ = simulated_log("flight", mount=by_name(mount).matrix, b_body=(0, 0, 0), seed=7)
    ref = wmm_field(LAT, LON, 0.4, parse_date(DATE))
    cov = track.covariates_at_mag()
    a = np.column_stack([cov[c] for c in ("ax", "ay", "az")])
    out = orientation_from_gravity(track.mag, -a / np.linalg.norm(a, axis=1, keepdims=True),
                                   ref["inclination_deg"])
    # ±20° of roll and pitch tell every rotation apart; the dip misfit is the 0.3 µT noise
    # over the 48 µT field (~0.4°)
    assert out["name"] == mount and out["ambiguous_with"] == [] and out["angle_error_deg"] < 1.0
    # the same through the diagnose hook, on a track without the attitude columns
    cols = {k: v for k, v in track.columns.items() if not k.startswith("att_")}
    from streamcal.calibration import Calibration
    identity = Calibration(K=np.eye(3) * ref["intensity_uT"], b=np.zeros(3),
                           field=ref["intensity_uT"])
    hook = log_attitude_reference(type(track)(cols, track.metadata), None, identity)
    assert hook["orientation"]["name"] == mount and "attitude_reference" not in hook


def test_level_vehicle_cannot_tell_yaw_mountings_from_gravity():
    from streamcal.fitting.orientation_gravity import orientation_from_gravity

    track, _ = simulated_log("still", duration_s=20, mount=by_name("YAW_90").matrix,
                             b_body=(0, 0, 0))
    cov = track.covariates_at_mag()
    a = np.column_stack([cov[c] for c in ("ax", "ay", "az")])
    out = orientation_from_gravity(track.mag, -a / np.linalg.norm(a, axis=1, keepdims=True), 64.0)
    assert out["name"] == "NONE" and "YAW_90" in out["ambiguous_with"]


def test_real_px4_frames_agree_with_the_model(flight_dir):
    """PX4's calibrated field, its logged attitude and the model at the simulator's home
    (Zurich, the PX4 SITL default; the log has no GPS) agree to a few µT: a frame or sign
    mistake in the quaternion or the NED field would leave tens of µT."""
    import datetime

    from streamcal.geomag import wmm_field
    from streamcal.inputs import autopilot_calibration, read_recording

    track = read_recording(flight_dir / "px4_pyulog_sample.ulg")
    ref = wmm_field(47.3977, 8.5456, 0.5, datetime.date(2016, 6, 1))
    out = attitude_reference(track, autopilot_calibration(track), ref=ref)["attitude_reference"]
    assert out["rms_uT_before"] < 3.0 and out["heading_error_deg"]["rms_before"] < 5.0
    assert out["n"] > 5000


def test_attitude_columns_are_no_misfit_covariates():
    from streamcal.diagnosis.misfit import localise

    track, _ = simulated_log("flight", duration_s=20, current_gain=np.array([0.1, 0, 0]))
    cov = track.covariates_at_mag()
    n = len(track.t_mag)
    out = localise(np.random.default_rng(0).normal(size=(n, 3)), np.ones(n, bool), track.t_mag,
                   track.mag, cov)
    assert "battery_current_a" in out["covariates"]
    assert not set(out["covariates"]) & {"att_qw", "att_qx", "att_qy", "att_qz"}


def test_report_shows_the_attitude_reference(tmp_path):
    from streamcal.report.figures_attitude import attitude_reference_figure

    track, _ = simulated_log("flight", duration_s=60, S=S_TRUE, b_body=B_TRUE)
    fig = attitude_reference_figure(track)
    assert fig is not None and fig.png.startswith(b"\x89PNG")
    path = tmp_path / "flight.csv"
    track.write(path)
    run = subprocess.run([sys.executable, "-m", "streamcal", "report", str(path), "-o",
                          str(tmp_path / "r.html")], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert fig.title in (tmp_path / "r.html").read_text(encoding="utf-8")
    cols = {k: v for k, v in track.columns.items() if not k.startswith("att_")}
    assert attitude_reference_figure(type(track)(cols, track.metadata)) is None


def test_cli_fit_attitude_and_its_refusals(tmp_path):
    gain = np.array([0.2, -0.1, 0.3])
    mount = by_name("YAW_90").matrix
    track, _ = simulated_log("flight", mount=mount, S=S_TRUE, b_body=B_TRUE, current_gain=gain)
    path = tmp_path / "flight.csv"
    track.write(path)

    def fit(*argv):
        return subprocess.run([sys.executable, "-m", "streamcal", "fit", str(path), *argv],
                              capture_output=True, text=True, timeout=600)

    run = fit("--attitude", "--add", "aux_interference", "--json")
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["orientation"]["name"] == "YAW_90"
    g = out["effects"]["aux_interference"]["channels"]["battery_current_a"]["g"]
    assert np.allclose(g, mount.T @ gain, atol=0.01)      # sensor frame
    bad = fit("--attitude", "--add", "temperature_offset")
    assert bad.returncode == 2 and "--add temperature_offset" in bad.stderr
    bad = fit("--attitude", "--add", "aux_interference=nope")
    assert bad.returncode == 2 and "battery_current_a" in bad.stderr
    meta = {k: v for k, v in track.metadata.items() if not k.startswith("gps_")}
    type(track)(track.columns, meta).write(path)
    nogps = fit("--attitude")
    assert nogps.returncode == 1 and "GPS" in nogps.stderr


def test_mounting_advice_composes_with_the_configured_rotation():
    from streamcal.fitting.attitude_reference import mounting_advice
    from streamcal.inputs.mount_rotations import by_number

    ardupilot = {"input_format": "ardupilot-dataflash", "param.COMPASS_ORIENT": "8"}
    # MAG is logged after COMPASS_ORIENT 8 (ROLL_180); a further YAW_90 makes ROLL_180_YAW_90
    # (10): Rz(90) Rx(180)
    advice = mounting_advice(ardupilot, by_name("YAW_90"))
    assert advice["configured"]["value"] == 8 and advice["set"]["value"] == 10
    assert mounting_advice(ardupilot, by_name("NONE"))["set"]["value"] == 8
    # the second parameter set (a log's second compass): COMPASS_ORIENT2
    second = {"input_format": "ardupilot-dataflash", "compass_params_index": "1",
              "param.COMPASS_ORIENT2": "0", "param.COMPASS_ORIENT": "8"}
    assert mounting_advice(second, by_name("YAW_90"))["set"] == {"param": "COMPASS_ORIENT2",
                                                                 "value": 2}
    # PX4's sensor_mag is the sensor's own frame: the rotation found is the one to set
    px4 = {"input_format": "px4-ulog", "mag_cal_params": "CAL_MAG1_", "mag_calibrated_by_px4": "no",
           "param.CAL_MAG1_ROT": "0", "param.SENS_BOARD_ROT": "4"}
    advice = mounting_advice(px4, by_name("ROLL_180"))
    assert advice["set"] == {"param": "CAL_MAG1_ROT", "value": 8}
    assert mounting_advice({"input_format": "track"}, by_name("ROLL_180")) == {}
    # ArduPilot's 26 (PITCH_180_YAW_90) is the matrix of 14 (ROLL_180_YAW_270)
    assert by_number(26).ardupilot == 14


def test_an_internal_compass_is_turned_by_the_board_rotation():
    """An internal compass turns with the board: PX4 ignores CAL_MAGn_ROT (−1) and turns it by
    SENS_BOARD_ROT, ArduPilot ignores COMPASS_ORIENTn (COMPASS_EXTERNAL 0) and turns it by
    AHRS_ORIENTATION; the advice names those."""
    from streamcal.fitting.attitude_reference import mounting_advice

    px4 = {"input_format": "px4-ulog", "mag_cal_params": "CAL_MAG1_", "mag_calibrated_by_px4": "no",
           "param.CAL_MAG1_ROT": "-1", "param.SENS_BOARD_ROT": "4"}
    advice = mounting_advice(px4, by_name("ROLL_180"))
    assert advice == {"configured": {"param": "SENS_BOARD_ROT", "value": 4},
                      "set": {"param": "SENS_BOARD_ROT", "value": 8}}
    # the calibrated topic is logged after the board rotation (YAW_180): ROLL_180 after it,
    # Rx(180) Rz(180) = Ry(180)
    calibrated = dict(px4, mag_calibrated_by_px4="yes")
    assert mounting_advice(calibrated, by_name("ROLL_180"))["set"] == {
        "param": "SENS_BOARD_ROT", "value": by_name("PITCH_180").px4}
    ardupilot = {"input_format": "ardupilot-dataflash", "compass_params_index": "1",
                 "param.COMPASS_ORIENT2": "8", "param.COMPASS_EXTERN2": "0",
                 "param.AHRS_ORIENTATION": "2"}
    advice = mounting_advice(ardupilot, by_name("NONE"))
    assert advice == {"configured": {"param": "AHRS_ORIENTATION", "value": 2},
                      "set": {"param": "AHRS_ORIENTATION", "value": 2}}
    external = dict(ardupilot, **{"param.COMPASS_EXTERN2": "1"})
    assert mounting_advice(external, by_name("NONE"))["set"] == {"param": "COMPASS_ORIENT2",
                                                                 "value": 8}


@pytest.mark.parametrize("firmware", ["ardupilot", "px4"])
def test_export_leaves_the_board_rotation_of_an_internal_compass(firmware):
    """The board rotation turns the IMU too: an export never writes it, and says what it would
    be when a rotation was found; the compass's own parameter is not written either."""
    from streamcal.export import export
    from streamcal.fitting.attitude_reference import fit_attitude_reference

    track, _ = simulated_log("flight", mount=by_name("YAW_90").matrix, b_body=B_TRUE)
    if firmware == "ardupilot":
        meta = dict(track.metadata, input_format="ardupilot-dataflash",
                    **{"param.COMPASS_ORIENT": "0", "param.COMPASS_EXTERNAL": "0",
                       "param.AHRS_ORIENTATION": "0"})
        own, board = "COMPASS_ORIENT", "AHRS_ORIENTATION"
    else:
        meta = dict(track.metadata, input_format="px4-ulog", mag_cal_params="CAL_MAG0_",
                    mag_calibrated_by_px4="yes",
                    **{"param.CAL_MAG0_ROT": "-1", "param.SENS_BOARD_ROT": "0"})
        own, board = "CAL_MAG0_ROT", "SENS_BOARD_ROT"
    cal = fit_attitude_reference(type(track)(track.columns, meta))
    assert cal.extra["orientation"]["set"] == {"param": board, "value": 2}
    text, notes = export(cal, firmware)
    assert own not in text and f"{board} 2" in text
    assert any(board in n and "accelerometer and gyro" in n for n in notes)


def test_export_sets_the_combined_orientation():
    from streamcal.export import export
    from streamcal.fitting.attitude_reference import fit_attitude_reference

    track, _ = simulated_log("flight", mount=by_name("YAW_90").matrix, b_body=B_TRUE)
    meta = dict(track.metadata, input_format="ardupilot-dataflash")
    meta["param.COMPASS_ORIENT"] = "8"
    cal = fit_attitude_reference(type(track)(track.columns, meta))
    assert cal.extra["orientation"]["set"]["value"] == 10
    text = export(cal, "ardupilot")[0]
    assert "COMPASS_ORIENT,10" in text.splitlines()


def _turned(track, mount):
    """``track`` with its magnetometer readings as a compass mounted by ``mount`` would give."""
    cols = dict(track.columns)
    mag = np.column_stack([cols[c] for c in ("mx", "my", "mz")])
    rows = track.mag_rows
    mag[rows] = mag[rows] @ by_name(mount).matrix
    cols.update(zip(("mx", "my", "mz"), mag.T))
    return type(track)(cols, track.metadata)


def test_a_low_reading_compass_is_scored_at_its_own_gain():
    # a compass reading 40 % low: held at the identity, the right rotation would misfit by
    # 0.4 × the field's swing (several µT) and could lose to a wrong one on a real log (16.BIN
    # turned by YAW_45 did); held at the readings' gain it misfits by the noise alone
    from streamcal.fitting.reference_fit import detect_rotation

    track, _ = simulated_log("flight", S=0.6 * np.eye(3), b_body=B_TRUE, seed=9)
    data, _ = attitude_data(_turned(track, "YAW_45"))
    fit, scores = detect_rotation(data.m, data.expected)
    assert fit.rotation.name == "YAW_45" and scores[0][0] == "YAW_45"
    # per-axis noise 0.3 µT (held at the identity instead: 6.0 µT, next best 10.7 µT)
    assert scores[0][1] < 0.5 and scores[1][1] > 5 * 0.5


@pytest.mark.parametrize("mount", ["YAW_45", "YAW_90", "ROLL_270_YAW_135"])
def test_real_log_turned_by_a_mounting_is_recognised(flight_dir, mount):
    from streamcal.inputs import read_recording

    track = read_recording(flight_dir / "ardupilot_erle_15-12-2014_16.BIN")
    base = attitude_reference(track)
    out = attitude_reference(_turned(track, mount))
    assert out["orientation"]["name"] == mount
    # the same field in another frame: the fit after undoing the mounting is the same
    assert out["attitude_reference"]["rms_uT_after"] == pytest.approx(
        base["attitude_reference"]["rms_uT_after"], rel=1e-3)


def test_diagnose_plots_include_the_attitude_reference(tmp_path):
    track, _ = simulated_log("flight", duration_s=60, S=S_TRUE, b_body=B_TRUE)
    path = tmp_path / "flight.csv"
    track.write(path)
    run = subprocess.run([sys.executable, "-m", "streamcal", "diagnose", str(path), "--plots",
                          str(tmp_path / "plots")], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "plots" / "attitude_reference.png").read_bytes().startswith(b"\x89PNG")


def test_readings_that_do_not_follow_the_attitude_are_said_so():
    from streamcal.errors import InsufficientDataError
    from streamcal.fitting.attitude_reference import fit_attitude_reference

    track, _ = simulated_log("flight", b_body=B_TRUE, seed=1)
    other, _ = simulated_log("flight", b_body=B_TRUE, seed=2)     # another flight's attitude
    cols = dict(track.columns)
    cols.update({k: v for k, v in other.columns.items() if k.startswith("att_")})
    mixed = type(track)(cols, track.metadata)
    out = attitude_reference(mixed)
    ref = out["attitude_reference"]
    assert ref["rms_uT_after"] is None and "do not follow" in ref["reason"]
    assert ref["rms_uT_before"] > 20 and out["orientation"] is None
    with pytest.raises(InsufficientDataError, match="do not follow"):
        fit_attitude_reference(mixed)


def test_px4_sensor_mag_before_is_turned_by_cal_mag_rot():
    """PX4 corrects a sensor_mag reading as R S (r − o), R = CAL_MAGn_ROT: the calibration in
    force, applied to a compass mounted ROLL_180 with CAL_MAG0_ROT = 8, matches the reference."""
    from streamcal.calibration import Calibration
    from streamcal.fitting.attitude_reference import px4_rotation

    track, truth = simulated_log("flight", mount=by_name("ROLL_180").matrix, b_body=B_TRUE)
    F = float(np.linalg.norm(truth["b_ned"]))
    meta = dict(track.metadata, input_format="px4-ulog", mag_cal_params="CAL_MAG0_",
                mag_calibrated_by_px4="no", **{"param.CAL_MAG0_ROT": "8"})
    px4 = type(track)(track.columns, meta)
    b_sensor = by_name("ROLL_180").matrix.T @ B_TRUE
    in_force = Calibration(K=F * np.eye(3), b=b_sensor, field=F, method="px4_params")
    assert px4_rotation(meta) == pytest.approx(by_name("ROLL_180").matrix)
    out = attitude_reference(px4, in_force)
    assert out["attitude_reference"]["rms_uT_before"] < 0.6
    assert out["orientation"]["name"] == "ROLL_180"
    assert out["orientation"]["set"] == {"param": "CAL_MAG0_ROT", "value": 8}
    internal = dict(meta, **{"param.CAL_MAG0_ROT": "-1", "param.SENS_BOARD_ROT": "2"})
    assert px4_rotation(internal) == pytest.approx(by_name("YAW_90").matrix)


def test_a_refused_diagnosis_still_says_what_the_attitude_reference_shows(tmp_path, capsys):
    """A vehicle that sat still (no diagnosis possible: b cannot come from it): exit 1 with the
    refusal, and the attitude reference's before/after all the same — the calibration in force
    against the World Magnetic Model rotated by the logged attitude (issue #24: a log that
    cannot be diagnosed still shows its heading error)."""
    from streamcal.cli import main

    track, _ = simulated_log("still", duration_s=30)
    path = tmp_path / "still.csv"
    track.write(path)
    assert main(["diagnose", str(path), "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["verdict"] is None and "hard-iron offset" in out["refused"]
    ref = out["attitude_reference"]
    assert ref["n"] > 0 and ref["rms_uT_after"] < ref["rms_uT_before"]
    assert main(["diagnose", str(path)]) == 1
    text = capsys.readouterr().out
    assert text.startswith("no diagnosis: ") and "heading error rms" in text


def test_the_reference_fit_weighs_with_the_shared_cauchy_width():
    """The reference fit's robust weights are the Cauchy weights of width
    streamcal.constants.CAUCHY_C σ̂ (the one width of every σ̂-scaled Cauchy fit) on its own
    converged residuals."""
    from streamcal.constants import CAUCHY_C

    rng = np.random.default_rng(4)
    e = rng.normal(size=(600, 3))
    e *= 48.0 / np.linalg.norm(e, axis=1, keepdims=True)
    m = e @ S_TRUE.T + B_TRUE + rng.normal(0.0, 0.4, e.shape)
    m[::25] += rng.normal(0.0, 30.0, m[::25].shape)           # outliers: weights well below 1
    fit = fit_reference(m, e)
    r = m - e @ fit.A.T - fit.b
    expected = 1.0 / (1.0 + np.sum(r * r, axis=1) / (CAUCHY_C * fit.scale) ** 2)
    assert fit.weights[::25].max() < 0.2
    np.testing.assert_allclose(fit.weights, expected, rtol=1e-7)
