"""PX4 ULog logs on a self-made log (tests/_selfmade_logs.py): what tests/test_inputs_flight.py
checks on the bundled pyulog samples — convert, content detection, each magnetometer topic
(sensor_mag; vehicle_magnetometer and sensor_combined with PX4's CAL_MAG0_* undone), aux channels
and units, the calibration in force (``--cal log``), a rotated calibration refused, truncated
logs."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.calibration import canonical_form
from streamcal.errors import InputError
from streamcal.inputs import autopilot_calibration, read_recording

from ._selfmade_logs import A_TRUE, B_TRUE, flight_slice, px4_params, write_ulog
from ._shared_checks import (check_convert_writes_the_track_read_recording_gives,
                             check_detected_from_content_not_name,
                             check_log_without_magnetometer_named,
                             check_px4_calibration_in_force,
                             check_truncated_log_read_to_last_message)

#: PX4 logs its parameters as float32: what the reader finds is the value rounded to that.
FLOAT32 = 1e-6


@pytest.fixture(scope="module")
def flight():
    return flight_slice(40.0, seed=4)


#: The three magnetometer topics the reader takes: the driver's reading, PX4's corrected field,
#: and that field riding in sensor_combined (older logs, as the bundled pyulog samples).
TOPICS = {"sensor_mag": {}, "vehicle_magnetometer": {"calibrated": True},
          "sensor_combined": {"calibrated": True, "combined": True}}


@pytest.fixture(scope="module", params=list(TOPICS))
def log(request, flight, tmp_path_factory):
    path = write_ulog(tmp_path_factory.mktemp("ulog") / "flight.ulg", flight,
                      **TOPICS[request.param])
    assert read_recording(path).metadata["mag_topic"].startswith(request.param)
    return path


def test_convert_writes_the_track_read_recording_gives(log, flight, tmp_path):
    check_convert_writes_the_track_read_recording_gives(log, flight, tmp_path, ("mag_topic",))


def test_detected_from_content_not_name(log, tmp_path):
    check_detected_from_content_not_name(log, tmp_path / "renamed.txt", "ulog", "px4-ulog")


def test_the_reading_is_the_sensors_whichever_topic_was_logged(log, flight):
    """sensor_mag is taken as read; vehicle_magnetometer (PX4's S (r − o)) has CAL_MAG0_* undone:
    both give back what the sensor read, in µT (gauss × 100)."""
    track = read_recording(log)
    np.testing.assert_allclose(track.mag, flight.mag_uT, atol=1e-4)   # float32 gauss
    np.testing.assert_allclose(track.t_mag, flight.t_mag - flight.t_mag[0], atol=1e-6)
    meta = track.metadata
    if meta["mag_calibrated_by_px4"] == "yes":
        assert meta["mag_calibration_undone"].startswith("CAL_MAG0_XOFF.. added back")
        assert meta["mag_axes"] == "body frame (PX4 rotated it)"
    else:
        assert meta["mag_topic"].startswith("sensor_mag")
        assert "temp" in track.columns and "sensor_mag.temperature" in meta["temp_source"]


def test_aux_channels_and_units(log, flight):
    track = read_recording(log)
    for name in ("act_out0", "act_out4", "throttle", "battery_current_a", "battery_voltage_v"):
        assert track.has(name), name
    assert "act_out5" not in track.columns   # a constant output is left out, and said
    assert track.metadata["actuator_outputs_dropped"] == "3 outputs constant or non-finite"
    rows = np.isfinite(track.columns["throttle"])
    np.testing.assert_allclose(track.columns["throttle"][rows], flight.throttle, atol=1e-6)
    # gauss × 100 = µT: PX4's corrected field has the simulated strength
    assert float(track.metadata["autopilot_field_uT"]) == pytest.approx(48.0, abs=0.1)


def test_calibration_in_force_maps_the_readings_as_px4_does(log, tmp_path, capsys):
    """--cal log: the CAL_MAG0_* in force as a Calibration gives PX4's own correction
    (export.px4.apply_px4) at the strength PX4's field has, and the true sensor model; diagnose
    runs against it and names its source; a converted track carries the same parameters."""
    cal, _ = check_px4_calibration_in_force(log, tmp_path, capsys)
    np.testing.assert_allclose(cal.b, B_TRUE, atol=1e-4)
    K, _ = canonical_form(A_TRUE)
    np.testing.assert_allclose(cal.K * 48.0 / cal.field, K, rtol=FLOAT32)


def test_a_rotated_calibration_is_kept_and_cal_log_refused(flight, tmp_path):
    """CAL_MAG0_ROT > 0 rotates PX4's field: the reader keeps the calibrated field and says why,
    and --cal log refuses to apply a calibration already applied."""
    path = write_ulog(tmp_path / "rot.ulg", flight, calibrated=True, params=px4_params(rot=4))
    track = read_recording(path)
    assert track.metadata["mag_calibration_undone"].startswith("could not: CAL_MAG0_ROT=4")
    assert np.linalg.norm(track.mag, axis=1).std() < 1.0   # PX4's (calibrated) field stays
    with pytest.raises(InputError, match="already applied to them"):
        autopilot_calibration(track)


@pytest.mark.parametrize("fraction", [0.5, 0.81])
def test_truncated_log_read_to_last_message_naming_file(flight, tmp_path, capsys, fraction):
    """A crash or a power cut: exit 0 without --skip-bad-rows, one stderr line naming the file
    and what was lost, the complete messages kept."""
    whole = write_ulog(tmp_path / "whole.ulg", flight)
    check_truncated_log_read_to_last_message(whole, tmp_path / "cut.ulg", fraction, tmp_path,
                                             capsys)


def test_log_without_magnetometer_names_the_topics_it_has(flight, tmp_path, capsys):
    path = write_ulog(tmp_path / "nomag.ulg", flight, with_mag=False)
    check_log_without_magnetometer_named(path, "no magnetometer topic.*sensor_combined", capsys)
