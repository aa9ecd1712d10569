"""ArduPilot's order of the compass corrections, which changed with the per-motor compensation:
Copter < 3.6, Plane < 3.9, Rover < 3.3 add COMPASS_MOT before the COMPASS_DIA/ODI matrix, later
firmware after it. Self-made logs (tests/_selfmade_logs.py) with a soft iron and a motor term
in force, written by each formula under the version text of a firmware that uses it: the reader
gets the sensor's reading back, the autopilot calibration rebuilds the logged field, and the
export writes the order asked for."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.export import export
from streamcal.export.ardupilot import apply_ardupilot
from streamcal.export.motor_check import held_out_check, read_parameters
from streamcal.fitting.attitude_reference import body_field
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.inputs.autopilot_cal import (MOTOR_AFTER_MATRIX, MOTOR_BEFORE_MATRIX,
                                            ardupilot_correction_order)

from ._selfmade_logs import flight_slice, write_dataflash

#: mG at full throttle: a motor term large enough that the matrix moves it by several mG.
MOT = np.array([150.0, -90.0, 210.0])
OLD_FIRMWARE = "ArduCopter V3.5.7 (b11c6af3)"
NEW_FIRMWARE = "ArduCopter V3.6.12 (a76b3ef7)"


@pytest.fixture(scope="module")
def flight():
    return flight_slice(30.0, seed=5)


@pytest.mark.parametrize("text, order", [
    ("ArduCopter V3.5.7 (b11c6af3)", MOTOR_BEFORE_MATRIX),
    ("APM:Copter V3.4-rc2 (f46a31d0)", MOTOR_BEFORE_MATRIX),
    ("ArduCopter V3.6.0 (9e3e7b2a)", MOTOR_AFTER_MATRIX),
    ("ArduCopter V4.3.7 (f1a2b3c4)", MOTOR_AFTER_MATRIX),
    ("ArduPlane V3.8.5 (1a2b3c4d)", MOTOR_BEFORE_MATRIX),
    ("ArduPlane V3.9.0 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("APM:Rover v3.2.0 (1a2b3c4d)", MOTOR_BEFORE_MATRIX),
    ("APM:Rover V3.3.1 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("ArduRover V4.2.3 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("Copter 3.5", MOTOR_BEFORE_MATRIX),
    ("ArduSub V3.4-RC3 (1a2b3c4d)", MOTOR_BEFORE_MATRIX),
    ("ArduSub V3.5.4 (1a2b3c4d)", MOTOR_BEFORE_MATRIX),
    ("ArduSub V4.0.0 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("AntennaTracker V1.0.0 (1a2b3c4d)", MOTOR_BEFORE_MATRIX),
    ("AntennaTracker V1.1.0 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("AntennaTracker V4.2.0 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    (None, MOTOR_AFTER_MATRIX),
    ("PX4 v1.12", MOTOR_AFTER_MATRIX),
])
def test_the_logged_version_decides_the_order(text, order):
    assert ardupilot_correction_order(text)[0] == order


@pytest.mark.parametrize("firmware, before", [(OLD_FIRMWARE, True), (NEW_FIRMWARE, False)])
def test_reading_recovered_in_the_order_of_the_logged_firmware(flight, tmp_path, firmware,
                                                                before):
    """Soft iron and motor offsets undone in the firmware's order: the sensor's reading to the
    logged 1 mG steps; the metadata name the order and why."""
    path = write_dataflash(tmp_path / "f.bin", flight, motor_comp=MOT, firmware=firmware,
                           motor_before_matrix=before)
    track = read_recording(path)
    np.testing.assert_allclose(track.mag, flight.mag_uT, atol=0.1)
    meta = track.metadata
    assert meta["ardupilot_correction_order"] == (MOTOR_BEFORE_MATRIX if before
                                                  else MOTOR_AFTER_MATRIX)
    assert meta["ardupilot_correction_order_from"].startswith("Copter 3.")
    assert meta["ardupilot_correction_order"] in meta["mag_soft_iron_undone"]


def test_no_vehicle_is_assumed_in_the_current_order():
    """Every vehicle ArduPilot logs has a known order: none falls to "assumed"."""
    for text in ("ArduSub V3.5.4", "AntennaTracker V1.0.0", "ArduSub V4.1.2",
                 "AntennaTracker V4.5.0"):
        assert "assumed" not in ardupilot_correction_order(text)[1]
    assert "assumed" in ardupilot_correction_order("PX4 v1.12")[1]


@pytest.mark.parametrize("version, msg, before", [
    ("ArduCopter V3.5.7 (b11c6af3)", "Frame: QUAD", True),
    ("ArduCopter V4.1.5 (b11c6af3)", OLD_FIRMWARE, False),   # VER wins over a stale MSG
])
def test_the_ver_message_names_the_firmware(flight, tmp_path, version, msg, before):
    """4.1 and later log a VER message: its firmware string decides the order (the MSG texts
    may not name the version, or name another)."""
    path = write_dataflash(tmp_path / "f.bin", flight, motor_comp=MOT, firmware=msg,
                           motor_before_matrix=before, version=version)
    track = read_recording(path)
    assert track.metadata["firmware"] == version
    np.testing.assert_allclose(track.mag, flight.mag_uT, atol=0.1)
    assert track.metadata["ardupilot_correction_order"] == (MOTOR_BEFORE_MATRIX if before
                                                            else MOTOR_AFTER_MATRIX)
    # the chunked reader (VER in the first piece only) and pymavlink's decoding say the same
    from streamcal.inputs.dataflash import read_dataflash_pymavlink
    from streamcal.inputs.dataflash_chunks import iter_dataflash_chunks

    last = list(iter_dataflash_chunks(path, piece_bytes=4096))[-1]
    assert last.metadata["firmware"] == read_dataflash_pymavlink(path).metadata["firmware"] \
        == version


def test_the_other_order_misses_the_reading(flight, tmp_path):
    """The same log read as if from the other firmware misses the reading by the matrix's
    effect on the motor term (so the order matters here, and the test above could fail)."""
    path = write_dataflash(tmp_path / "f.bin", flight, motor_comp=MOT, firmware=NEW_FIRMWARE,
                           motor_before_matrix=True)
    miss = np.abs(read_recording(path).mag - flight.mag_uT).max()
    assert miss > 0.5


@pytest.mark.parametrize("firmware, before", [(OLD_FIRMWARE, True), (NEW_FIRMWARE, False)])
def test_autopilot_calibration_rebuilds_the_logged_field(flight, tmp_path, firmware, before):
    """``--cal autopilot`` on either firmware's log: applied with the throttle, the logged field
    (its norm, to the 1 mG steps); the motor term is the firmware's, in the sensor frame."""
    path = write_dataflash(tmp_path / "f.bin", flight, motor_comp=MOT, firmware=firmware,
                           motor_before_matrix=before)
    track = read_recording(path)
    cal = autopilot_calibration(track)
    assert cal.extra["ardupilot_correction_order"] == track.metadata["ardupilot_correction_order"]
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    logged = []
    while (m := reader.recv_match(type="MAG")) is not None:
        logged.append((m.MagX, m.MagY, m.MagZ))
    field = cal.apply_field(track.mag, {"throttle": flight.throttle_at_mag})
    np.testing.assert_allclose(np.linalg.norm(field, axis=1),
                               np.linalg.norm(np.array(logged, float), axis=1) / 10.0, atol=0.09)
    g = np.array(cal.effects["aux_interference"]["channels"]["throttle"]["g"])
    S_inv_mot = np.linalg.solve(_S(track.metadata), MOT)
    np.testing.assert_allclose(g, -(MOT if before else S_inv_mot) / 10.0, rtol=1e-5)


def _S(meta: dict) -> np.ndarray:
    p = {k[6:]: float(v) for k, v in meta.items() if k.startswith("param.")}
    return np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                     [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                     [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])


def _calibration_of(flight, tmp_path, firmware, before):
    path = write_dataflash(tmp_path / "f.bin", flight, motor_comp=MOT, firmware=firmware,
                           motor_before_matrix=before)
    track = read_recording(path)
    return track, autopilot_calibration(track)


@pytest.mark.parametrize("firmware, before", [(OLD_FIRMWARE, True), (NEW_FIRMWARE, False)])
def test_export_for_the_logged_firmware_gives_its_compass_mot_back(flight, tmp_path, firmware,
                                                                    before):
    """The calibration in force read from a log and exported for that log's firmware: the
    COMPASS_MOT it was flown with (7 significant digits), in either order."""
    _, cal = _calibration_of(flight, tmp_path, firmware, before)
    params = read_parameters(export(cal, "ardupilot", firmware)[0], "ardupilot")
    np.testing.assert_allclose([params[f"COMPASS_MOT_{a}"] for a in "XYZ"], MOT, rtol=1e-5)
    assert params["COMPASS_MOTCT"] == 1


def test_export_in_either_order_corrects_as_streamcal_does(flight, tmp_path):
    """A calibration from an old firmware's log exported for it ("Copter 3.5") and by default
    (the newest order, said in the file): each firmware's formula gives streamcal's own
    correction; the newest parameters under the old formula do not."""
    track, cal = _calibration_of(flight, tmp_path, OLD_FIRMWARE, True)
    thr = flight.throttle_at_mag
    own = body_field(cal, track.mag, {"throttle": thr}, track.metadata)
    old_text = export(cal, "ardupilot", "Copter 3.5")[0]
    new_text = export(cal, "ardupilot")[0]
    old, new = (read_parameters(t, "ardupilot") for t in (old_text, new_text))
    for params, order in ((old, MOTOR_BEFORE_MATRIX), (new, MOTOR_AFTER_MATRIX)):
        f = apply_ardupilot(params, 10.0 * track.mag, thr, order) / 10.0
        np.testing.assert_allclose(f, own, atol=2e-3)
    assert "f = S (r + COMPASS_OFS + COMPASS_MOT * c)" in old_text
    assert "these are for 'offsets, matrix, motor'" in new_text
    crossed = apply_ardupilot(new, 10.0 * track.mag, thr, MOTOR_BEFORE_MATRIX) / 10.0
    assert np.abs(crossed - own).max() > 0.5


def test_held_out_check_uses_the_order_of_the_calibration_in_force(tmp_path):
    """An old firmware's log with a wrong motor term in force goes through the held-out check:
    ArduPilot's formula (in that firmware's order) and PX4's give the same figures, and the
    refitted term corrects. (Exported and applied in one order, any order gives these figures:
    what the order changes is the COMPASS_MOT to load, tested above.)"""
    path = write_dataflash(tmp_path / "flight.bin", flight_slice(120.0, 1, motor_uT=4.0),
                           messages=("IMU", "CURR", "BAT"), motor_comp=MOT,
                           firmware=OLD_FIRMWARE, motor_before_matrix=True)
    track = read_recording(path)
    out = held_out_check(track, autopilot_calibration(track), "throttle")
    for name in ("before", "refit", "after"):
        for key, value in out[name]["ardupilot"].items():
            assert out[name]["px4"][key] == pytest.approx(value, abs=2e-3), (name, key)
    assert out["after"]["ardupilot"]["spread_pct"] < 0.6 * out["before"]["ardupilot"]["spread_pct"]


def test_cli_firmware_version(flight, tmp_path, capsys):
    _, cal = _calibration_of(flight, tmp_path, OLD_FIRMWARE, True)
    path = tmp_path / "cal.json"
    path.write_text(cal.to_json())
    out = tmp_path / "c.parm"
    assert main(["export", str(path), "--format", "ardupilot", "--firmware-version",
                 "ArduCopter V3.5.7", "-o", str(out)]) == 0
    params = read_parameters(out.read_text(), "ardupilot")
    np.testing.assert_allclose([params[f"COMPASS_MOT_{a}"] for a in "XYZ"], MOT, rtol=1e-5)
    capsys.readouterr()
    assert main(["export", str(path), "--format", "ardupilot", "--firmware-version",
                 "3.5"]) == 2
    assert "--firmware-version '3.5': expected an ArduPilot vehicle" in capsys.readouterr().err
    assert main(["export", str(path), "--format", "px4", "--firmware-version",
                 "Copter 3.5"]) == 2
    assert "applies to --format ardupilot" in capsys.readouterr().err


def test_fit_cal_autopilot_then_export_round_trip(tmp_path, capsys):
    """``fit OLD.bin --cal autopilot --add aux_interference=throttle``, ``export``: the refined
    calibration remembers the log's order; exported for that firmware and applied with its
    formula it corrects the raw readings as streamcal's own correction does (|f|), and the default
    export says it was written for the newest order."""
    flight = flight_slice(60.0, 1, motor_uT=4.0)
    log = write_dataflash(tmp_path / "old.bin", flight, messages=("IMU", "CURR", "BAT"),
                          motor_comp=MOT, firmware=OLD_FIRMWARE, motor_before_matrix=True)
    new = tmp_path / "new.json"
    assert main(["fit", str(log), "--cal", "autopilot", "--add", "aux_interference=throttle",
                 "-o", str(new)]) == 0
    out = tmp_path / "old.parm"
    assert main(["export", str(new), "--format", "ardupilot", "--firmware-version",
                 "Copter 3.5", "-o", str(out)]) == 0
    assert main(["export", str(new), "--format", "ardupilot", "-o",
                 str(tmp_path / "newest.parm")]) == 0
    assert "these are for 'offsets, matrix, motor'" in (tmp_path / "newest.parm").read_text()
    from streamcal.calibration import Calibration

    cal = Calibration.load(new)
    assert cal.extra["ardupilot_correction_order"] == MOTOR_BEFORE_MATRIX
    track = read_recording(log)
    thr = np.interp(track.t_mag, flight.t_mag, flight.throttle_at_mag)
    own = body_field(cal, track.mag, {"throttle": thr}, track.metadata)
    f = apply_ardupilot(read_parameters(out.read_text(), "ardupilot"), 10.0 * track.mag, thr,
                        MOTOR_BEFORE_MATRIX) / 10.0
    # the refit turns the exported matrix's frame by the unobservable rotation: compare |f|
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), np.linalg.norm(own, axis=1), atol=2e-3)
