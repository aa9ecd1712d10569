"""ArduPilot DataFlash logs on a self-made log (tests/_selfmade_logs.py): what
tests/test_inputs_flight.py and tests/test_dataflash_bulk.py check on the real logs — convert,
content detection, offsets / soft iron / motor offsets undone, aux channels and their units, the
COMPASS_* calibration, the bulk decoder against pymavlink, damaged and truncated logs."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.calibration import canonical_form
from streamcal.inputs import autopilot_calibration, read_recording

from ._selfmade_logs import (A_TRUE, B_TRUE, FIRMWARE, LAYOUT, ardupilot_params, flight_slice,
                             write_dataflash)
from ._shared_checks import (check_bulk_track_equals_pymavlink_track,
                             check_convert_writes_the_track_read_recording_gives,
                             check_detected_from_content_not_name,
                             check_log_without_magnetometer_named,
                             check_truncated_log_read_to_last_message,
                             check_damaged_message_resynchronised,
                             check_garbage_run_skipped_and_named, check_random_damage,
                             check_string_where_a_number_is_needed_named,
                             check_unknown_format_character_named,
                             check_walk_follows_every_message, cut_inside_header_and_body)

#: The calibration is rebuilt from the param.* metadata, which keeps 6 significant digits (the
#: real logs' DIA = 1, ODI = 0 are exact there; this log's soft iron is not).
PARAM_DIGITS = 1e-6


@pytest.fixture(scope="module")
def flight():
    return flight_slice(40.0, seed=3)


@pytest.fixture(scope="module")
def log(flight, tmp_path_factory):
    return write_dataflash(tmp_path_factory.mktemp("df") / "flight.bin", flight)


def _mag_messages(path):
    """MAG rows straight from pymavlink: (MagX/Y/Z, OfsX/Y/Z, MOfsX/Y/Z) in mG."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows = []
    while (m := reader.recv_match(type="MAG")) is not None:
        rows.append((m.MagX, m.MagY, m.MagZ, m.OfsX, m.OfsY, m.OfsZ, m.MOfsX, m.MOfsY, m.MOfsZ))
    rows = np.array(rows, float)
    return rows[:, :3], rows[:, 3:6], rows[:, 6:]


def _S(params):
    """COMPASS_DIA/ODI as logged (PARM values are float32)."""
    params = {k: float(np.float32(v)) for k, v in params.items()}
    return np.array([[params["COMPASS_DIA_X"], params["COMPASS_ODI_X"], params["COMPASS_ODI_Y"]],
                     [params["COMPASS_ODI_X"], params["COMPASS_DIA_Y"], params["COMPASS_ODI_Z"]],
                     [params["COMPASS_ODI_Y"], params["COMPASS_ODI_Z"], params["COMPASS_DIA_Z"]]])


def test_convert_writes_the_track_read_recording_gives(log, flight, tmp_path):
    track = check_convert_writes_the_track_read_recording_gives(log, flight, tmp_path,
                                                                ("firmware",))
    assert track.metadata["firmware"] == FIRMWARE


def test_detected_from_content_not_name(log, tmp_path):
    check_detected_from_content_not_name(log, tmp_path / "renamed.csv", "dataflash",
                                         "ardupilot-dataflash")


def test_offsets_and_soft_iron_undone_back_to_the_sensor_reading(log, flight):
    """S (10 m + Ofs) + MOfs gives back the logged MagX/Y/Z, and m is what the sensor read
    (to the logged 1 mG steps)."""
    track = read_recording(log)
    logged, ofs, mofs = _mag_messages(log)
    S = _S(ardupilot_params())
    order = np.argsort(track.t_mag, kind="stable")
    np.testing.assert_allclose((10.0 * track.mag[order] + ofs) @ S.T + mofs, logged, atol=1e-9)
    assert np.any(ofs != 0) and not np.allclose(S, np.eye(3))   # both undone, not skipped
    # one logged mG step is 0.1 µT; through S⁻¹ (near 1) at most about 0.06 µT per axis
    assert np.max(np.abs(track.mag - flight.mag_uT)) < 0.1
    meta = track.metadata
    assert "subtracted" in meta["mag_offsets_undone"]
    assert "-120,70,-200" in meta["mag_offsets_undone"]
    assert "inverse of the PARM COMPASS_DIA/ODI" in meta["mag_soft_iron_undone"]
    assert meta["mag_motor_offsets_undone"] == "none (MAG.MOfs all 0)"


def test_motor_offsets_undone_and_the_compass_mot_term_rebuilt(flight, tmp_path):
    """COMPASS_MOTCT = 1 (throttle): the logged MOfs are subtracted per sample and the
    autopilot calibration carries the motor term; applied with the throttle it maps the readings
    onto the field the autopilot logged."""
    mot = np.array([40.0, -25.0, 60.0])   # mG at full throttle
    path = write_dataflash(tmp_path / "mot.bin", flight, motor_comp=mot)
    track = read_recording(path)
    logged, _, mofs = _mag_messages(path)
    assert np.ptp(mofs, axis=0).min() > 10 and "per sample" in \
        track.metadata["mag_motor_offsets_undone"]
    assert "(offsets, matrix, motor: Copter 4.0 adds COMPASS_MOT after" in \
        track.metadata["mag_soft_iron_undone"]
    np.testing.assert_allclose(track.mag, flight.mag_uT, atol=0.1)
    cal = autopilot_calibration(track)
    g = cal.effects["aux_interference"]["channels"]["throttle"]["g"]
    np.testing.assert_allclose(g, -np.linalg.solve(_S(ardupilot_params()), mot) / 10.0,
                               rtol=PARAM_DIGITS)
    # with the throttle at each MAG sample, the logged field up to its 1 mG (0.1 µT) steps
    field = cal.apply_field(track.mag, {"throttle": flight.throttle_at_mag})
    np.testing.assert_allclose(np.linalg.norm(field, axis=1),
                               np.linalg.norm(logged, axis=1) / 10.0, atol=0.09)
    # without the motor term the same readings miss it by up to ~6 µT
    bare = autopilot_calibration(read_recording(write_dataflash(tmp_path / "b.bin", flight)))
    miss = np.linalg.norm(bare.apply_field(track.mag), axis=1) - np.linalg.norm(logged, axis=1) / 10
    assert np.max(np.abs(miss)) > 3.0


def test_aux_channels_their_units_and_the_parameters(log, flight, tmp_path):
    track = read_recording(log)
    for name in ("rcou_c1", "rcou_c5", "battery_current_a", "battery_voltage_v", "throttle"):
        assert track.has(name), name
    assert "rcou_c6" not in track.columns and "rcou_c6" in track.metadata["rcou_constant_dropped"]
    rows = np.isfinite(track.columns["throttle"])
    np.testing.assert_allclose(track.columns["throttle"][rows], flight.throttle, atol=1e-3)
    assert track.metadata["throttle_source"] == "CURR.Throttle / 1000 (0..1)"
    assert track.metadata["param.COMPASS_OFS_X"] == "-120"
    # an older layout: CURR's integer Volt is centivolts; an output that is no PWM is dropped
    old = read_recording(write_dataflash(tmp_path / "old.bin", flight, c7_not_pwm=True,
                                         messages=("IMU", "RCOU", "CURR")))
    volts = old.columns["battery_voltage_v"]
    np.testing.assert_allclose(volts[np.isfinite(volts)], flight.volts, atol=0.006)
    assert "rcou_c7" not in old.columns
    last = 50_000 + 10 * (len(flight.t_ch) - 1)
    assert f"rcou_c7 (values 50000..{last} outside 0..3000 us" in old.metadata["rcou_dropped"]


def test_autopilot_calibration_reproduces_the_logged_field_and_the_truth(log):
    track = read_recording(log)
    cal = autopilot_calibration(track)
    logged, _, _ = _mag_messages(log)
    field = cal.apply_field(track.mag)
    np.testing.assert_allclose(np.linalg.norm(field, axis=1),
                               np.linalg.norm(logged, axis=1) / 10.0, rtol=PARAM_DIGITS)
    K, _ = canonical_form(A_TRUE)
    np.testing.assert_allclose(cal.K * 48.0 / cal.field, K, rtol=PARAM_DIGITS)
    np.testing.assert_allclose(cal.b, B_TRUE, atol=1e-9)


@pytest.mark.parametrize("fraction", [0.5, 0.73])
def test_truncated_log_read_to_last_message_naming_file(log, tmp_path, capsys, fraction):
    """A crash or a power cut: exit 0 without --skip-bad-rows, one stderr line naming the file
    and what was lost, the complete messages kept."""
    check_truncated_log_read_to_last_message(log, tmp_path / "cut.BIN", fraction, tmp_path,
                                             capsys)


def test_log_without_magnetometer_names_the_message(flight, tmp_path, capsys):
    path = write_dataflash(tmp_path / "nomag.bin", flight, with_mag=False)
    check_log_without_magnetometer_named(path, "no MAG messages.*IMU", capsys)


def test_bulk_track_equals_pymavlink_track(log):
    check_bulk_track_equals_pymavlink_track(log)


def test_walk_follows_every_message_of_a_clean_log(log):
    check_walk_follows_every_message(log)


def test_garbage_run_skipped_and_named(log, tmp_path):
    check_garbage_run_skipped_and_named(log, tmp_path)


def test_damaged_message_resynchronised(log, tmp_path):
    check_damaged_message_resynchronised(log, tmp_path)


def test_truncated_inside_header_and_body(log, tmp_path):
    assert len(cut_inside_header_and_body(log, tmp_path)) == 2


def test_unknown_format_character_named(log, tmp_path):
    check_unknown_format_character_named(log, tmp_path)


def test_string_where_a_number_is_needed_named(log, tmp_path):
    check_string_where_a_number_is_needed_named(log, tmp_path, LAYOUT["MAG"][1].encode())


@pytest.mark.parametrize("seed", range(12))
def test_random_damage_gives_a_track_or_a_named_error(log, tmp_path, seed):
    check_random_damage(log.read_bytes()[:120_000], tmp_path, seed, fmt_block=3000)
