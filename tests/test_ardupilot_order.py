"""ArduPilot's order of the compass corrections, which changed with the per-motor compensation:
Copter < 3.6, Plane < 3.9, Rover < 3.4 add COMPASS_MOT before the COMPASS_DIA/ODI matrix, later
firmware after it. Self-made logs (tests/_selfmade_logs.py) with a soft iron and a motor term
in force, written by each formula under the version text of a firmware that uses it: the reader
gets the sensor's reading back, the autopilot calibration rebuilds the logged field, and the
export writes the order asked for."""
from __future__ import annotations

import numpy as np
import pytest

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
    ("ArduRover V3.4.0 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("ArduRover V4.2.3 (1a2b3c4d)", MOTOR_AFTER_MATRIX),
    ("Copter 3.5", MOTOR_BEFORE_MATRIX),
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
