"""Real flight-controller logs (data/real/flight under STREAMCAL_SHARED): read, convert, offsets
undone, truncated copies read to their last complete message."""
import shutil
from pathlib import Path

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.errors import InputError
from streamcal.inputs import autopilot_calibration, detect, read_recording
from streamcal.inputs.track import Track

from ._shared_checks import check_px4_calibration_in_force

BINS = ["ardupilot_erle_Erle-Brain3.BIN", "ardupilot_erle_PXFv2.0b_Rpi.BIN",
        "ardupilot_erle_15-12-2014_16.BIN"]
ULGS = ["px4_pyulog_sample.ulg", "px4_pyulog_sample_logging_tagged_and_default_params.ulg",
        "px4_pyulog_sample_px4_events.ulg"]


def _mag_messages(path):
    """MAG rows straight from pymavlink: (MagX/Y/Z, OfsX/Y/Z) in mG."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    logged, ofs = [], []
    while (m := reader.recv_match(type="MAG")) is not None:
        logged.append((m.MagX, m.MagY, m.MagZ))
        ofs.append((m.OfsX, m.OfsY, m.OfsZ))
    return np.array(logged, float), np.array(ofs, float)


@pytest.mark.slow
@pytest.mark.parametrize("name", BINS + ULGS)
def test_every_flight_log_converts(flight_dir, tmp_path, name, capsys):
    out = tmp_path / "track.csv"
    assert main(["convert", str(flight_dir / name), "-o", str(out)]) == 0
    track = Track.read(out)
    direct = read_recording(flight_dir / name)
    assert len(track) == len(direct) and len(track.t_mag) > 100
    assert np.all(np.diff(track.t) >= 0) and track.t[0] == 0.0
    np.testing.assert_array_equal(track.mag, direct.mag)
    assert track.mag_unit == "uT"
    assert track.has("accel") and track.has("gyro")
    for key in ("input_format", "source", "mag_axes", "units", "time_origin"):
        assert key in track.metadata, key


def test_detected_from_content_not_name(flight_dir, tmp_path):
    bin_copy = tmp_path / "renamed.csv"
    shutil.copy(flight_dir / BINS[0], bin_copy)
    ulg_copy = tmp_path / "renamed.txt"
    shutil.copy(flight_dir / ULGS[0], ulg_copy)
    assert detect(bin_copy) == "dataflash" and detect(ulg_copy) == "ulog"
    assert read_recording(bin_copy).metadata["input_format"] == "ardupilot-dataflash"


@pytest.mark.parametrize("name,readme_mG", [(BINS[0], (696, 37)), (BINS[1], (250, 62)),
                                            (BINS[2], (373, 16))])
@pytest.mark.slow
def test_dataflash_offsets_undone_and_units(flight_dir, name, readme_mG):
    """raw µT × 10 + OfsX/Y/Z gives back the logged MagX/Y/Z exactly; the logged field has the
    magnitude the README states."""
    path = flight_dir / name
    track = read_recording(path)
    logged, ofs = _mag_messages(path)
    assert len(track.mag) == len(logged)
    order = np.argsort(track.t_mag, kind="stable")  # merge kept MAG rows in log order
    np.testing.assert_allclose(track.mag[order] * 10.0 + ofs, logged, atol=1e-9)
    norm = np.linalg.norm(logged, axis=1)
    assert abs(norm.mean() - readme_mG[0]) < 1.0 and abs(norm.std() - readme_mG[1]) < 1.0
    assert np.any(ofs != 0)  # the check would be empty otherwise
    assert "subtracted" in track.metadata["mag_offsets_undone"]


@pytest.mark.slow
def test_dataflash_aux_columns(flight_dir):
    pxf = read_recording(flight_dir / BINS[1])
    for name in ("rcou_c1", "rcou_c4", "battery_current_a", "battery_voltage_v", "throttle"):
        assert pxf.has(name), name
    assert 0 <= np.nanmin(pxf.columns["throttle"]) and np.nanmax(pxf.columns["throttle"]) <= 1
    volts = pxf.columns["battery_voltage_v"]
    assert 5 < np.nanmedian(volts) < 30  # centivolts converted
    old = read_recording(flight_dir / BINS[2])
    assert old.has("rcou_c1") and old.has("throttle")
    assert "rcou_c7" not in old.columns and "rcou_c7" in old.metadata["rcou_dropped"]
    assert old.metadata["param.COMPASS_OFS_X"] == "-36"


@pytest.mark.slow
def test_autopilot_calibration_reproduces_logged_field(flight_dir):
    """The Calibration built from COMPASS_* maps the undone readings back onto the field the
    autopilot logged (here DIA = 1, ODI = MOT = 0: logged = raw + offsets)."""
    track = read_recording(flight_dir / BINS[1])
    cal = autopilot_calibration(track)
    logged, _ = _mag_messages(flight_dir / BINS[1])
    field = cal.apply_field(track.mag)
    np.testing.assert_allclose(np.linalg.norm(field, axis=1),
                               np.linalg.norm(logged, axis=1) / 10.0, rtol=1e-9)


def test_ulog_px4_calibration_undone(flight_dir):
    from pyulog import ULog

    path = flight_dir / ULGS[0]
    track = read_recording(path)
    assert track.metadata["mag_calibrated_by_px4"] == "yes"
    ulog = ULog(str(path))
    p = ulog.initial_parameters
    d = next(d for d in ulog.data_list if d.name == "sensor_combined")
    cal_g = np.column_stack([d.data[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(float)
    off = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    scale = np.array([p[f"CAL_MAG0_{a}SCALE"] for a in "XYZ"])
    expected = {tuple(np.round(row, 6)) for row in (cal_g / scale + off) * 100.0}
    got = {tuple(np.round(row, 6)) for row in track.mag}
    assert got <= expected and len(got) > 1000


def test_px4_calibration_in_force_reproduces_its_corrected_field(flight_dir, tmp_path, capsys):
    """--cal log on a PX4 ULog: the Calibration built from the CAL_MAG0_* in force maps the
    track's (undone) readings onto the norms of PX4's own correction (export.px4.apply_px4),
    at the strength of the field PX4 logged; diagnose runs against it and names its source."""
    cal, params = check_px4_calibration_in_force(flight_dir / ULGS[0], tmp_path, capsys)
    np.testing.assert_allclose(cal.b, [100.0 * params[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])


def test_px4_cal_log_refused_when_the_readings_are_already_calibrated(flight_dir):
    track = read_recording(flight_dir / ULGS[0])
    track.metadata["mag_calibration_undone"] = ("could not: CAL_MAG0_ROT=4, SENS_BOARD_ROT=0 "
                                                "rotate the field")
    with pytest.raises(InputError, match="already applied to them"):
        autopilot_calibration(track)


def test_ulog_aux_and_units(flight_dir):
    events = read_recording(flight_dir / ULGS[2])
    assert events.has("act_out0") and events.has("battery_voltage_v")
    norm = np.linalg.norm(events.mag, axis=1)
    assert 20 < norm.mean() < 70  # gauss × 100 = µT, an Earth-like field


def _cut(src: Path, dst: Path, fraction: float) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


@pytest.mark.parametrize("name,suffix", [(BINS[0], ".BIN"), (ULGS[0], ".ulg")])
def test_truncated_log_read_to_last_message(flight_dir, tmp_path, capsys, name, suffix):
    """A log cut in half (a crash, a power cut): exit 0 without --skip-bad-rows, one stderr line
    naming the file and what was lost, the first half's magnetometer samples kept."""
    cut = _cut(flight_dir / name, tmp_path / f"cut{suffix}", 0.5)
    out = tmp_path / "out.csv"
    assert main(["convert", str(cut), "-o", str(out)]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if str(cut) in line]
    assert len(err) == 1 and "truncated" in err[0] and "lost" in err[0]
    track = Track.read(out)
    assert "truncated" in track.metadata["read_warnings"]
    whole = read_recording(flight_dir / name)
    assert 0.2 * len(whole.t_mag) < len(track.t_mag) < 0.8 * len(whole.t_mag)


def test_log_without_magnetometer_names_message(flight_dir, tmp_path, capsys):
    head = _cut(flight_dir / BINS[0], tmp_path / "head.bin", 0.0005)
    with pytest.raises(InputError, match="MAG"):
        read_recording(head, skip_bad_rows=True)
    assert main(["fit", str(head)]) == 2
    assert str(head) in capsys.readouterr().err
