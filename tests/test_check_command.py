"""``streamcal check CAL RECORDING`` (issue #24 item 4): a motor compensation fitted on one flight,
checked on another flight of the same vehicle against the calibration in force there, with each
firmware's own formula (:mod:`streamcal.export.motor_check`). Two simulated flights with
attitude, GPS and battery current (:func:`streamcal.sim.flight.simulated_log`, the autopilot's
COMPASS_* in their metadata) and two self-made DataFlash/ULog flights with throttle
(tests/_selfmade_logs.py, as tests/test_motor_compensation_loaded.py builds them)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.export.motor_check import (compare, figures, firmware_field, held_out_check,
                                          motor_signal)
from streamcal.fitting.attitude_reference import attitude_data
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.sim.flight import simulated_log

from ._selfmade_logs import flight_slice, write_dataflash
from .test_motor_compensation_loaded import MOTOR_UT, _write

S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])
GAIN = np.array([0.2, -0.1, 0.3])     # µT/A in the body frame: 1..13 µT over 5..35 A
KEYS = {"cal", "recording", "firmware", "in_force", "n", "n_heading", "channels", "before",
        "after", "compare"}
FIGURES = {"spread_pct", "spread_robust_pct", "heading_rms_deg", "heading_p95_deg"}


def _simulated_flight(path, seed: int):
    """A flight of the simulated vehicle as a track whose metadata carry the autopilot's
    COMPASS_* (exact but for the motor field, which they do not compensate)."""
    track, truth = simulated_log("flight", S=S_TRUE, b_body=B_TRUE, current_gain=GAIN, seed=seed)
    S_ap = np.linalg.inv(S_TRUE)
    params = {f"COMPASS_OFS_{a}": -10.0 * B_TRUE[k] for k, a in enumerate("XYZ")}
    params.update({f"COMPASS_DIA_{a}": S_ap[k, k] for k, a in enumerate("XYZ")})
    params.update(COMPASS_ODI_X=S_ap[0, 1], COMPASS_ODI_Y=S_ap[0, 2], COMPASS_ODI_Z=S_ap[1, 2])
    track.metadata.update({f"param.{k}": repr(float(v)) for k, v in params.items()})
    track.metadata["autopilot_field_uT"] = repr(float(np.linalg.norm(truth["b_ned"])))
    track.write(path)
    return path


@pytest.fixture(scope="module")
def two_flights(tmp_path_factory):
    """(new.json fitted on flight 1, flight 2)."""
    d = tmp_path_factory.mktemp("check")
    first, second = _simulated_flight(d / "one.csv", 5), _simulated_flight(d / "two.csv", 6)
    new = d / "new.json"
    assert main(["fit", str(first), "--cal", "autopilot", "--add",
                 "aux_interference=battery_current_a", "-o", str(new)]) == 0
    return new, second


def _json(argv, capsys) -> dict:
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_check_on_another_flight_lowers_spread_and_heading(two_flights, capsys):
    new, second = two_flights
    out = _json(["check", str(new), str(second)], capsys)
    assert KEYS <= out.keys() and "heading" not in out
    track = read_recording(second)
    assert out["n"] == len(track.t_mag) and out["n_heading"] == out["n"]
    assert out["channels"] == {"ardupilot": "battery_current_a", "px4": "battery_current_a"}
    # the numbers are motor_check's own, recomputed here
    cov, m = track.covariates_at_mag(), np.asarray(track.mag, float)
    data, _ = attitude_data(track)
    in_force, cal = autopilot_calibration(track), Calibration.load(new)
    for fw in ("ardupilot", "px4"):
        assert out["before"][fw] == figures(
            firmware_field(in_force, fw, m, motor_signal(in_force, fw, cov)), data)
        assert out["after"][fw] == figures(
            firmware_field(cal, fw, m, motor_signal(cal, fw, cov)), data)
        assert out["after"][fw].keys() == FIGURES
    before, after = out["before"]["ardupilot"], out["after"]["ardupilot"]
    # 0.3 µT noise on a ~21 µT horizontal field: ~0.8° of heading noise is the floor
    assert after["heading_rms_deg"] < 1.0 < 5.0 < before["heading_rms_deg"]
    assert after["spread_pct"] < 0.15 * before["spread_pct"]
    assert out["compare"]["ardupilot"]["better"] and not out["compare"]["ardupilot"]["worse"]
    for key, value in out["after"]["streamcal"].items():
        assert after[key] == pytest.approx(value, abs=2e-3)

    capsys.readouterr()
    assert main(["check", str(new), str(second)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"On this flight {new.name} lowers the field-magnitude spread from ")
    assert "and the heading error from" in first and "ArduPilot's formula" in first
    assert f"{before['spread_pct']:.1f} %" in first and "worse" not in first


def test_a_wrong_motor_term_is_called_worse(two_flights, tmp_path, capsys):
    """The fitted term with its sign turned: the words say worse and advise keeping the
    calibration in force; the exit code is still 0."""
    new, second = two_flights
    cal = Calibration.load(new)
    term = cal.effects["aux_interference"]["channels"]["battery_current_a"]
    effects = {"aux_interference": {"channels": {"battery_current_a": {
        **term, "g": [-v for v in term["g"]]}}}}
    wrong = tmp_path / "wrong.json"
    cal.replace(effects=effects).save(wrong)
    out = _json(["check", str(wrong), str(second)], capsys)
    comp = out["compare"]["ardupilot"]
    assert comp["worse"] and not comp["better"] and comp["spread"] == "higher"
    assert out["after"]["ardupilot"]["spread_pct"] > out["before"]["ardupilot"]["spread_pct"]
    assert main(["check", str(wrong), str(second)]) == 0
    text = capsys.readouterr().out
    assert "raises the field-magnitude spread" in text.splitlines()[0]
    assert "worse than the calibration in force; keep the calibration in force." in text


@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
def test_selfmade_logs_without_attitude(kind, tmp_path, capsys):
    """Two self-made flights of one vehicle (throttle, no GPS): the spread falls on the second
    with the firmware's formula of the log's own kind; the heading says why it is missing."""
    suffix = ".bin" if kind == "ardupilot" else ".ulg"
    first, second = tmp_path / f"first{suffix}", tmp_path / f"second{suffix}"
    _write(kind, first, flight_slice(120.0, 1, motor_uT=MOTOR_UT))
    _write(kind, second, flight_slice(120.0, 2, motor_uT=MOTOR_UT))
    new = tmp_path / "new.json"
    assert main(["fit", str(first), "--cal", "autopilot", "--add", "aux_interference=throttle",
                 "-o", str(new)]) == 0
    out = _json(["check", str(new), str(second)], capsys)
    assert out["firmware"] == kind and out["n_heading"] == 0 and "GPS" in out["heading"]
    before, after = out["before"][kind], out["after"][kind]
    assert "heading_rms_deg" not in after
    # 4 µT over the throttle range on a 48 µT field: ~2 % of spread, the sensor's own ~0.8 %
    assert after["spread_pct"] < 0.6 * before["spread_pct"]
    assert main(["check", str(new), str(second)]) == 0
    text = capsys.readouterr().out
    formula = "ArduPilot's formula" if kind == "ardupilot" else "PX4's formula"
    assert "lowers the field-magnitude spread" in text.splitlines()[0] and formula in text
    assert text.splitlines()[1].startswith("No heading error: the log has no GPS position")


@pytest.mark.parametrize("fit_on", ["first", "last"])
def test_split_is_the_held_out_check(two_flights, fit_on, capsys):
    new, second = two_flights
    out = _json(["check", str(new), str(second), "--split", fit_on], capsys)
    track = read_recording(second)
    expected = held_out_check(track, autopilot_calibration(track), "battery_current_a",
                              fit_on=fit_on)
    for key in ("before", "refit", "after", "streamcal", "g_uT", "n_checked", "checked_s"):
        assert out[key] == expected[key], key
    # half a flight can mislead: fitted on the first half (one turn) of this one, the refit
    # turns the heading on the other; the words follow the figures either way
    comp = compare(expected["before"]["ardupilot"], expected["after"]["ardupilot"])
    assert out["compare"]["ardupilot"] == comp
    assert main(["check", str(new), str(second), "--split", fit_on]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"Fitted on the {fit_on} half of this flight")
    assert ("keep the calibration in force" in first) == comp["worse"]
    verb = "raises" if comp["worse"] else "lowers"
    assert f"a motor term on battery_current_a {verb}" in first


def test_bad_input_is_one_line_and_exit_2(two_flights, tmp_path, capsys):
    new, second = two_flights
    no_mag = write_dataflash(tmp_path / "nomag.bin", flight_slice(10.0, 1),
                             messages=("IMU", "CURR"), with_mag=False)
    throttle_only = write_dataflash(tmp_path / "throttle.bin", flight_slice(10.0, 1),
                                    messages=("IMU", "CURR"))
    not_cal = tmp_path / "not_cal.json"
    not_cal.write_text('{"hello": 1}\n')
    counts = tmp_path / "counts.csv"
    counts.write_text("time,Bx,By,Bz\n" + "".join(f"{0.1 * k},{300 + k},{-200 - k},{100}\n"
                                                  for k in range(100)))
    cases = [([str(new), str(no_mag)], "nomag.bin"),
             ([str(not_cal), str(second)], "not_cal.json"),
             ([str(new), str(throttle_only)], "battery_current_a"),
             (["autopilot", str(second), "--split", "first"], "no motor term"),
             ([str(new), str(second), "--lat", "47"], "--lat and --lon"),
             ([str(new), str(counts), "--columns", "mx=Bx,my=By,mz=Bz,t=time", "--unit",
               "counts"], "in counts")]
    for argv, what in cases:
        capsys.readouterr()
        assert main(["check", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and what in err, err
        assert "Traceback" not in err and err.startswith("streamcal check: error: ")


@pytest.mark.slow
def test_real_2014_copter_split(flight_dir, tmp_path, capsys):
    """The 2014 copter (GPS, attitude, throttle): the held-out check of its own flight through
    the command gives held_out_check's figures, heading included."""
    log = flight_dir / "ardupilot_erle_15-12-2014_16.BIN"
    new = tmp_path / "new.json"
    assert main(["fit", str(log), "--cal", "autopilot", "--add", "aux_interference=throttle",
                 "-o", str(new)]) == 0
    out = _json(["check", str(new), str(log), "--split", "first"], capsys)
    track = read_recording(log)
    expected = held_out_check(track, autopilot_calibration(track), "throttle")
    assert out["after"] == expected["after"] and out["before"] == expected["before"]
    assert "heading_rms_deg" in out["after"]["ardupilot"]
    out = _json(["check", str(new), str(log)], capsys)
    assert out["n_heading"] > 1000 and out["firmware"] == "ardupilot"


def test_compare_tolerances():
    """A figure changes when it moves by more than its floor and 10 % of its value."""
    before = {"spread_pct": 5.0, "heading_rms_deg": 2.0}
    assert compare(before, {"spread_pct": 5.4, "heading_rms_deg": 2.4}) | {"rule": ""} == {
        "spread": "same", "heading": "same", "worse": False, "better": False, "rule": ""}
    out = compare(before, {"spread_pct": 4.4, "heading_rms_deg": 2.6})
    assert (out["spread"], out["heading"], out["worse"]) == ("lower", "higher", True)
    out = compare({"spread_pct": 0.5}, {"spread_pct": 0.35})
    assert (out["spread"], out["heading"], out["better"]) == ("lower", None, True)


def test_second_compass(tmp_path, capsys):
    """A calibration fitted for compass 1 (exported as COMPASS_*2_*) is checked with the same
    formula on compass 1; read at another compass, a line on stderr says which to give."""
    from ._dataflash_log import write_flight

    log = tmp_path / "two.bin"
    write_flight(log, [{"ofs": (30.0, -20.0, 10.0)},
                       {"ofs": (-50.0, 40.0, 5.0), "err": np.array([150.0, 0.0, 0.0])}],
                 motct=1, mot=(20.0, -10.0, 30.0))
    new = tmp_path / "c1.json"
    assert main(["fit", str(log), "--compass", "1", "--cal", "autopilot", "--add",
                 "aux_interference=throttle", "-o", str(new)]) == 0
    out = _json(["check", str(new), str(log), "--compass", "1"], capsys)
    track = read_recording(log, compass=1)
    cov, m = track.covariates_at_mag(), np.asarray(track.mag, float)
    in_force = autopilot_calibration(track)
    assert out["before"]["ardupilot"] == figures(
        firmware_field(in_force, "ardupilot", m, motor_signal(in_force, "ardupilot", cov)), None)
    # compass 1's calibration in force misses 15 µT of hard iron
    assert out["after"]["ardupilot"]["spread_pct"] < 0.2 * out["before"]["ardupilot"]["spread_pct"]
    # without --compass the compass it was fitted for is read (said), not the default compass 0
    assert main(["check", str(new), str(log), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["after"] == out["after"]
    assert "reading compass 1" in captured.err
    assert main(["check", str(new), str(log), "--compass", "0"]) == 0
    err = capsys.readouterr().err
    assert "fitted for compass 1" in err and "--compass 1" in err
