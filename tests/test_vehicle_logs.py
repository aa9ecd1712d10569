"""Logs of vehicles streamcal has no real log of (issue #24's acceptance runs on such flights):
self-made ArduCopter 3.3–4.x, ArduPlane 3.x/4.x and ArduRover 3.x/4.x logs
(:mod:`tests._vehicle_logs`) with two or three compasses, attitude and GPS, one or two batteries
whose current runs 0–70 A, and each firmware's own throttle message. Each is read and checked
against the truth it was written from."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.inputs import read_recording

from ._vehicle_logs import VEHICLES, Compass, soft_iron, write_vehicle_log


def _compasses(n: int) -> list[Compass]:
    return [Compass(A=soft_iron(k), b=np.array([12.0, -7.0, 20.0]) * (k + 1) / 2,
                    g=np.array([0.05, -0.02, 0.08]) * (1 - 0.4 * k)) for k in range(n)]


def _column(track, name):
    values = np.asarray(track.columns[name], float)
    return values[np.isfinite(values)]


@pytest.mark.parametrize("vehicle", ["copter4", "copter40", "copter36", "copter34", "plane4",
                                     "rover4"])
def test_each_battery_is_its_own_channel(vehicle, tmp_path):
    """BAT's instance field is ``Inst`` (4.1 on) or ``Instance`` (4.0), BAT2 before (3.6), CUR2
    before that (3.4–3.5): battery 0's
    current alone is ``battery_current_a`` (0–70 A), battery 1's is ``battery2_current_a`` —
    not the two batteries' rows mixed into one channel."""
    path = tmp_path / f"{vehicle}.bin"
    truth = write_vehicle_log(path, vehicle, _compasses(2), seconds=30.0, two_batteries=True,
                              second_volts=lambda t: 15.1 - 0.01 * t)
    track = read_recording(path)
    np.testing.assert_allclose(_column(track, "battery_current_a"),
                               truth.current.astype(np.float32), rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(_column(track, "battery2_current_a"),
                               truth.current2.astype(np.float32), rtol=1e-6)


@pytest.mark.parametrize("vehicle, source", [
    ("copter4", "CTUN.ThO (0..1)"), ("copter33", "CURR.Throttle / 1000 (0..1)"),
    ("plane4", "CTUN.ThO / 100 (0..1; a plane's throttle, logged in percent)"),
    ("plane3", "CTUN.ThrOut / 100 (0..1; a plane's throttle, logged in percent)"),
    ("plane32", "CTUN.ThrOut / 100 (0..1; a plane's throttle, logged in percent)"),
    ("rover3", "CTUN.ThrOut / 100 (0..1; a rover's throttle, logged in percent)"),
    ("rover4", "THR.ThrOut / 100 (0..1; a rover's throttle, logged in percent)")])
def test_throttle_in_each_vehicles_units(vehicle, source, tmp_path):
    """The throttle each vehicle logs becomes 0..1: a copter's CTUN.ThO as is, CURR.Throttle
    /1000, a plane's CTUN.ThO/ThrOut and a rover's CTUN/THR.ThrOut (percent) /100 — not 100×
    or 10× off — and a rover's THR is read (not four RCOU channels that include its steering)."""
    path = tmp_path / f"{vehicle}.bin"
    truth = write_vehicle_log(path, vehicle, _compasses(2), seconds=30.0)
    track = read_recording(path)
    assert track.metadata["throttle_source"] == source
    # logged as float, int16 percent (0.01 steps) or int16 per mille (0.001 steps)
    np.testing.assert_allclose(_column(track, "throttle"), truth.throttle, atol=0.0051)


def test_plane_curr_throttle_is_the_pilots_input_in_percent(tmp_path):
    """ArduPlane 3.0–3.2 logged CURR.Throttle = channel_throttle->control_in (0–100 %, the
    pilot's input): beside CTUN.ThrOut (the output) it is not the throttle; a plane log whose
    CTUN has no throttle reads it as percent (/100, not /1000) and says it is the input."""
    path = tmp_path / "plane32.bin"
    truth = write_vehicle_log(path, "plane32", _compasses(2), seconds=30.0)
    track = read_recording(path)
    assert track.metadata["curr_throttle_ignored"].startswith("CURR.Throttle: a plane's pilot")
    np.testing.assert_allclose(_column(track, "throttle"), truth.throttle, atol=0.0051)
    assert np.max(np.abs(truth.throttle_in - truth.throttle)) > 0.1
    # the same log without CTUN's throttle fields: CURR.Throttle, percent, the pilot's input
    import tests._vehicle_logs as vl

    layouts = dict(vl.VEHICLES["plane32"][1])
    layouts["CTUN"] = ("Qcccchf", "TimeUS,NavRoll,Roll,NavPitch,Pitch,RdrOut,AccY")
    saved = vl.VEHICLES["plane32"]
    vl.VEHICLES["plane32"] = (saved[0], layouts, *saved[2:4], ("CTUN", "RdrOut", 100.0))
    try:
        write_vehicle_log(path, "plane32", _compasses(2), seconds=30.0)
    finally:
        vl.VEHICLES["plane32"] = saved
    track = read_recording(path)
    assert track.metadata["throttle_source"].startswith("CURR.Throttle / 100 (0..1; a plane's "
                                                         "pilot throttle input")
    np.testing.assert_allclose(_column(track, "throttle"), truth.throttle_in, atol=0.0051)


def _pymavlink_rows(path, name, fields):
    """{instance: (n, len(fields)) array} of message ``name``, straight from pymavlink."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows: dict = {}
    while (msg := reader.recv_match(type=name)) is not None:
        rows.setdefault(int(getattr(msg, "I", 0)), []).append([getattr(msg, f) for f in fields])
    return {k: np.array(v, float) for k, v in rows.items()}


def _angles(u, v):
    cos = np.sum(u * v, 1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_compass_all_figures_against_a_plain_recomputation(tmp_path, capsys):
    """diagnose --compass all --json's autopilot-calibration figures equal those recomputed
    here with plain numpy from pymavlink's MAG (the field the autopilot corrected, mG) and IMU
    rows: the 3-D and horizontal angles (median, p95) and the share of samples over ArduPilot's
    consistency limits (AP_Compass.h: 90°, 60° in body X-Y, 200 mG X-Y length difference).
    Compass 2's motor field (3 mG/A along X) is not compensated (COMPASS_MOT3 0): at 0–70 A it
    crosses the 200 mG limit part of the flight."""
    compasses = _compasses(3)
    compasses[1].ofs_error = np.array([60.0, -40.0, 0.0])
    compasses[2].g = np.array([0.3, 0.0, 0.0])
    compasses[2].mot_in_force = np.zeros(3)
    path = tmp_path / "copter4_three.bin"
    write_vehicle_log(path, "copter4", compasses, seconds=90.0)
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) in (0, 1)
    got = {(p["a"], p["b"]): p for p in json.loads(capsys.readouterr().out)["consistency"]
           if p["calibration"] == "autopilot"}
    mag = _pymavlink_rows(path, "MAG", ["TimeUS", "MagX", "MagY", "MagZ"])
    acc = _pymavlink_rows(path, "IMU", ["TimeUS", "AccX", "AccY", "AccZ"])[0]
    assert set(got) == {(0, 1), (0, 2), (1, 2)}
    shares = {}
    for (a, b), pair in got.items():
        ta, fa = mag[a][:, 0], mag[a][:, 1:]
        fb = mag[b][:, 1:]
        assert np.array_equal(ta, mag[b][:, 0]) and np.array_equal(ta, acc[:, 0])
        g = acc[:, 1:] / np.linalg.norm(acc[:, 1:], axis=1, keepdims=True)
        ha = fa - np.sum(fa * g, 1, keepdims=True) * g
        hb = fb - np.sum(fb * g, 1, keepdims=True) * g
        angle, horizontal = _angles(fa, fb), _angles(ha, hb)
        body_xy = _angles(np.c_[fa[:, :2], 0 * ta], np.c_[fb[:, :2], 0 * ta])
        over = (angle > 90) | (body_xy > 60) | (np.linalg.norm(fa[:, :2] - fb[:, :2], axis=1) > 200)
        assert pair["n"] == len(ta)
        # the log's MOfs are rounded to 1 mG, streamcal rebuilds the motor term from COMPASS_MOT
        # × current: up to 0.5 mG per axis on a ~240 mG horizontal field, ≤ 0.1°
        for key, values in (("angle_deg", angle), ("xy_angle_deg", horizontal)):
            assert pair[f"{key}_median"] == pytest.approx(np.median(values), abs=0.1)
            assert pair[f"{key}_p95"] == pytest.approx(np.percentile(values, 95), abs=0.1)
        assert pair["fraction_inconsistent"] == pytest.approx(np.mean(over), abs=2 / len(ta))
        shares[(a, b)] = np.mean(over)
    # compass 1's 72 mG offset error crosses the 60° body X-Y limit only where the tilted
    # vehicle leaves little field in its X-Y plane; compass 2's motor field far more often
    assert 0.1 < shares[(0, 2)] < 0.6 and shares[(0, 1)] < 0.5 * shares[(0, 2)]


def _parameters(text: str, sep: str, name_col: int, value_col: int) -> dict:
    rows = [line.split(sep) for line in text.splitlines() if line and not line.startswith("#")]
    return {r[name_col]: float(r[value_col]) for r in rows}


@pytest.mark.parametrize("vehicle, firmware", [("copter4", None), ("copter33", "Copter 3.3")])
def test_motor_term_of_a_0_to_70_a_flight_in_each_firmwares_units(vehicle, firmware, tmp_path):
    """A 0–70 A flight whose compass 1 sees 0.05, −0.02, 0.08 µT per ampere that COMPASS_MOT2
    does not compensate (0 in force): ``fit --compass 1 --cal autopilot --add
    aux_interference=battery_current_a`` then ``export`` gives COMPASS_MOT2_* in mG/A with
    COMPASS_MOTCT 2 (= −10 · S · g with the exported COMPASS_DIA2/ODI2 matrix S) and PX4's
    CAL_MAG1_xCOMP in G/kA (= −10 · g) with CAL_MAG_COMP_TYP 2, each within the noise of the
    truth (2 mG per axis over 1200 samples: σ ≈ 0.003 mG/A). A Copter 3.3 log (CURR in
    centi-amps, MAG2, the motor term added before the matrix) exported for that firmware:
    COMPASS_MOT2 = −10 · g."""
    compasses = _compasses(2)
    g = np.array([0.05, -0.02, 0.08])
    compasses[1].g, compasses[1].mot_in_force = g, np.zeros(3)
    log = tmp_path / f"{vehicle}_70A.bin"
    truth = write_vehicle_log(log, vehicle, compasses, seconds=120.0)
    assert truth.current.min() == 0 and truth.current.max() == 70
    cal = tmp_path / "new.json"
    assert main(["fit", str(log), "--compass", "1", "--cal", "autopilot", "--add",
                 "aux_interference=battery_current_a", "-o", str(cal)]) == 0
    ardupilot, px4 = tmp_path / "new.parm", tmp_path / "new.params"
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(ardupilot),
                 *(["--firmware-version", firmware] if firmware else [])]) == 0
    assert main(["export", str(cal), "--format", "px4", "-o", str(px4)]) == 0
    ap = _parameters(ardupilot.read_text(), ",", 0, 1)
    assert ap["COMPASS_MOTCT"] == 2 and "COMPASS_MOT_X" not in ap
    S = np.array([[ap["COMPASS_DIA2_X"], ap["COMPASS_ODI2_X"], ap["COMPASS_ODI2_Y"]],
                  [ap["COMPASS_ODI2_X"], ap["COMPASS_DIA2_Y"], ap["COMPASS_ODI2_Z"]],
                  [ap["COMPASS_ODI2_Y"], ap["COMPASS_ODI2_Z"], ap["COMPASS_DIA2_Z"]]])
    mot = np.array([ap[f"COMPASS_MOT2_{a}"] for a in "XYZ"])
    np.testing.assert_allclose(mot, -10.0 * (g if firmware else S @ g), atol=0.012)
    p = _parameters(px4.read_text(), "\t", 2, 3)
    assert p["CAL_MAG_COMP_TYP"] == 2 and "CAL_MAG0_XCOMP" not in p
    np.testing.assert_allclose([p[f"CAL_MAG1_{a}COMP"] for a in "XYZ"], -10.0 * g, atol=0.012)


def test_a_battery_without_current_sensor_is_not_damage(tmp_path, monkeypatch):
    """ArduPilot logs BAT.Curr as NaN when the monitor measures no current (a voltage-only
    second battery): that column is left out and said, the battery's voltage kept, and nothing
    is called damaged."""
    import tests._vehicle_logs as logs

    profile = logs.flight_profile

    def voltage_only_second(*args, **kw):
        t, att, current, current2, throttle = profile(*args, **kw)
        return t, att, current, current2 * np.nan, throttle

    monkeypatch.setattr(logs, "flight_profile", voltage_only_second)
    path = tmp_path / "nan_current.bin"
    write_vehicle_log(path, "copter4", _compasses(2), seconds=20.0, two_batteries=True,
                      second_volts=lambda t: 15.1 - 0.01 * t)
    track = read_recording(path)
    assert "battery2_current_a" not in track.aux_names
    assert len(_column(track, "battery2_voltage_v")) == 200
    assert track.metadata["battery2_not_measured"].startswith("battery2_current_a")
    assert "damaged" not in track.metadata.get("read_warnings", "")


def test_a_calibration_file_is_applied_to_the_compass_it_was_fitted_for(tmp_path, capsys):
    """``diagnose LOG --cal c1.json`` (c1.json fitted for compass 1) without --compass reads
    compass 1, says so, and gives what ``--compass 1`` gives; compass 0's readings under
    compass 1's calibration would have a far larger residual."""
    compasses = _compasses(2)
    compasses[1].b = np.array([-30.0, 25.0, 10.0])
    log = tmp_path / "two.bin"
    write_vehicle_log(log, "copter4", compasses, seconds=60.0)
    cal = tmp_path / "c1.json"
    assert main(["fit", str(log), "--compass", "1", "--cal", "autopilot", "-o", str(cal)]) == 0
    capsys.readouterr()
    runs = {}
    for extra in ([], ["--compass", "1"], ["--compass", "0"]):
        assert main(["diagnose", str(log), "--cal", str(cal), "--json", *extra]) in (0, 1)
        captured = capsys.readouterr()
        runs[tuple(extra)] = (json.loads(captured.out), captured.err)
    followed, err = runs[()]
    assert "reading compass 1" in err
    given = runs[("--compass", "1")][0]
    assert followed["ladder"][0]["rms"] == given["ladder"][0]["rms"]
    assert runs[("--compass", "0")][0]["ladder"][0]["rms"] > 5 * given["ladder"][0]["rms"]


@pytest.mark.parametrize("vehicle", ["copter4", "copter34", "plane3", "plane32", "rover4"])
def test_read_in_pieces_equals_read_whole(vehicle, tmp_path):
    """The bounded-memory reader of long logs gives the whole-log Track on every layout here
    (second batteries, each vehicle's throttle), compass 1."""
    from streamcal.inputs.dataflash import read_dataflash
    from streamcal.inputs.dataflash_chunks import iter_dataflash_chunks

    path = tmp_path / f"{vehicle}.bin"
    write_vehicle_log(path, vehicle, _compasses(2), seconds=40.0, two_batteries=True,
                      second_volts=lambda t: 15.1 - 0.01 * t)
    whole = read_dataflash(path, compass=1)
    parts = list(iter_dataflash_chunks(path, compass=1, piece_bytes=20_000))
    assert len(parts) > 3
    for name in whole.columns:
        joined = np.concatenate([np.asarray(p.columns[name], float) for p in parts])
        np.testing.assert_array_equal(joined, np.asarray(whole.columns[name], float))


def test_the_pairs_ardupilot_itself_compares(tmp_path, capsys):
    """ArduPilot's consistency test compares the primary (COMPASS_PRIMARY, here 1) with each
    compass used for yaw: with COMPASS_USE3 0 only pair 0–1 is one it checks; the JSON marks
    each pair and the text names them."""
    path = tmp_path / "three.bin"
    write_vehicle_log(path, "copter36", _compasses(3), seconds=30.0,
                      extra_params={"COMPASS_PRIMARY": 1, "COMPASS_USE3": 0})
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) in (0, 1)
    pairs = json.loads(capsys.readouterr().out)["consistency"]
    assert {(p["a"], p["b"]): p["ardupilot_checks"] for p in pairs} == {
        (0, 1): True, (0, 2): False, (1, 2): False}
    assert main(["diagnose", str(path), "--compass", "all"]) in (0, 1)
    assert "compass used for yaw only: 0–1\n" in capsys.readouterr().out + "\n"


def test_second_compass_mounted_turned_exports_compass_orient2(tmp_path):
    """Compass 1 (external) mounted turned 90° in yaw while COMPASS_ORIENT2 says 0: ``fit
    --compass 1 --attitude`` finds YAW_90 and the export sets COMPASS_ORIENT2 2 (not COMPASS_ORIENT, the
    first compass's) with COMPASS_OFS2 in the vehicle frame after that rotation: −10 · b."""
    from streamcal.inputs.mount_rotations import by_name

    compasses = _compasses(2)
    compasses[1].mount = np.array(by_name("YAW_90").matrix)
    compasses[1].g = np.zeros(3)     # no motor field: the fit has no term for one
    log = tmp_path / "turned.bin"
    # external: ArduPilot ignores COMPASS_ORIENTn of an internal compass (the board's rotation)
    write_vehicle_log(log, "copter4", compasses, seconds=120.0,
                      extra_params={"COMPASS_EXTERN2": 1})
    cal, parm = tmp_path / "c1.json", tmp_path / "c1.parm"
    assert main(["fit", str(log), "--compass", "1", "--attitude", "-o", str(cal)]) == 0
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(parm)]) == 0
    text = parm.read_text()
    params = _parameters(text, ",", 0, 1)
    assert params["COMPASS_ORIENT2"] == 2 and "COMPASS_ORIENT" not in params
    assert "# COMPASS_ORIENT2 2: " in text
    np.testing.assert_allclose([params[f"COMPASS_OFS2_{a}"] for a in "XYZ"],
                               -10.0 * compasses[1].b, atol=1.5)


def test_a_fit_without_motor_term_zeroes_the_motor_compensation_it_was_fitted_without(
        tmp_path):
    """Compass 1's motor field (0.03, −0.012, 0.048 µT/A) is compensated in the log by
    COMPASS_MOT2, which the reader undoes: a fit without a motor term (``--attitude``) puts the
    field's mean (≈35 A of it) into its offsets. Its export sets COMPASS_MOT2 (and PX4's
    CAL_MAG1_xCOMP) to 0 and says why — keeping the old term would remove that mean twice."""
    compasses = _compasses(2)
    log = tmp_path / "mot_in_force.bin"
    truth = write_vehicle_log(log, "copter4", compasses, seconds=120.0)
    cal, parm, params = tmp_path / "c1.json", tmp_path / "c1.parm", tmp_path / "c1.params"
    assert main(["fit", str(log), "--compass", "1", "--attitude", "-o", str(cal)]) == 0
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(parm)]) == 0
    assert main(["export", str(cal), "--format", "px4", "-o", str(params)]) == 0
    ap = _parameters(parm.read_text(), ",", 0, 1)
    assert [ap[f"COMPASS_MOT2_{a}"] for a in "XYZ"] == [0, 0, 0] and "COMPASS_MOTCT" not in ap
    assert "# COMPASS_MOT2 set to 0:" in parm.read_text()
    ofs = np.array([ap[f"COMPASS_OFS2_{a}"] for a in "XYZ"])
    mean_field = compasses[1].b + compasses[1].g * truth.current.mean()
    assert np.linalg.norm(ofs + 10 * mean_field) < 0.3 * np.linalg.norm(ofs + 10 * compasses[1].b)
    p = _parameters(params.read_text(), "\t", 2, 3)
    assert [p[f"CAL_MAG1_{a}COMP"] for a in "XYZ"] == [0, 0, 0]
    # a bench calibration (no log, no motor compensation in force) leaves COMPASS_MOT alone
    from streamcal.calibration import Calibration

    bench = Calibration.load(cal)
    bench = bench.replace(extra={k: v for k, v in bench.extra.items()
                                 if k != "motor_field_in_readings"})
    bench.save(tmp_path / "bench.json")
    assert main(["export", str(tmp_path / "bench.json"), "--format", "ardupilot", "-o",
                 str(tmp_path / "bench.parm")]) == 0
    assert "COMPASS_MOT2_X" not in (tmp_path / "bench.parm").read_text()


def test_compass_scale_in_force_is_reset_with_the_matrix(tmp_path):
    """ArduPilot 4.x multiplies compass 1's field by COMPASS_SCALE2 (1.1 here) before the
    matrix. The exported COMPASS_DIA2/ODI2 hold the whole scale, so the export sets
    COMPASS_SCALE2 1; ArduPilot's formula with the exported parameters then gives the
    calibration's field strength, not 10 % more."""
    from streamcal.calibration import Calibration
    from streamcal.export.ardupilot import apply_ardupilot

    log = tmp_path / "scaled.bin"
    write_vehicle_log(log, "copter4", _compasses(2), seconds=60.0,
                      extra_params={"COMPASS_SCALE2": 1.1})
    cal, parm = tmp_path / "c1.json", tmp_path / "c1.parm"
    assert main(["fit", str(log), "--compass", "1", "--cal", "autopilot", "-o", str(cal)]) == 0
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(parm)]) == 0
    ap = _parameters(parm.read_text(), ",", 0, 1)
    assert ap["COMPASS_SCALE2"] == 1 and "COMPASS_SCALE" not in ap
    first = {k.replace("2_", "_"): v for k, v in ap.items()}
    track = read_recording(log, compass=1)
    current = np.interp(track.t_mag, track.t[np.isfinite(track.columns["battery_current_a"])],
                        _column(track, "battery_current_a"))
    field = apply_ardupilot(first, 10.0 * np.asarray(track.mag), current)
    strength = np.median(np.linalg.norm(field, axis=1)) / 10.0
    assert strength == pytest.approx(Calibration.load(cal).field, rel=0.01)


@pytest.mark.parametrize("external", [1, 0])
def test_the_text_says_which_parameter_to_set_for_a_turned_compass(tmp_path, capsys, external):
    """``diagnose --compass 1`` of a compass mounted YAW_90 where COMPASS_ORIENT2 says 0 names
    what to set: COMPASS_ORIENT2 2 for an external compass; for an internal one the board's
    AHRS_ORIENTATION, said to turn the IMU too."""
    from streamcal.inputs.mount_rotations import by_name

    compasses = _compasses(2)
    compasses[1].mount = np.array(by_name("YAW_90").matrix)
    compasses[1].g = np.zeros(3)
    log = tmp_path / "turned.bin"
    write_vehicle_log(log, "copter4", compasses, seconds=120.0,
                      extra_params={"COMPASS_EXTERN2": external})
    assert main(["diagnose", str(log), "--compass", "1", "--cal", "log"]) == 0
    out = capsys.readouterr().out
    if external:
        assert "set COMPASS_ORIENT2 2 (now 0;" in out
    else:
        assert "set AHRS_ORIENTATION 2 (now 0; the board's rotation" in out
