"""Motor compensation a user loads (issue #24 item 4): fitted from one flight against the
autopilot's calibration, exported in the firmware's own parameters, and applied with that
firmware's own correction formula to *another* flight of the same vehicle — the field-magnitude
spread and the heading error fall. Self-made logs (`tests/_selfmade_logs.py`): the same
sensor and the same motor coupling (4 µT over the flight's throttle range along one direction),
two different flights."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.export.ardupilot import apply_ardupilot
from streamcal.export.common import polar
from streamcal.export.motor_check import read_parameters
from streamcal.export.px4 import apply_px4
from streamcal.inputs import read_recording

from ._selfmade_logs import (ardupilot_params, flight_slice, px4_params, write_dataflash,
                             write_ulog)

MOTOR_UT = 4.0


def _write(kind: str, path, flight):
    if kind == "ardupilot":
        return write_dataflash(path, flight, messages=("IMU", "CURR"))
    return write_ulog(path, flight, topics=("sensor_combined", "actuator_controls_0"))


def _corrected(kind: str, params: dict, track, compensated: bool) -> np.ndarray:
    """The firmware's corrected field (its units) of a track's raw readings."""
    m = np.asarray(track.mag, float)
    throttle = track.covariates_at_mag()["throttle"] if compensated else None
    if kind == "ardupilot":
        return apply_ardupilot(params, 10.0 * m, throttle)
    return apply_px4(params, m / 100.0, throttle)


def _own(cal: Calibration, track, kind: str) -> np.ndarray:
    """Streamcal's own corrected field of a track (every fitted channel at its value) in the
    firmware's symmetric frame (``Uᵀ f``, :func:`polar`) and units."""
    cov = track.covariates_at_mag()
    channels = cal.effects["aux_interference"]["channels"]
    U, _ = polar(cal.field * np.linalg.inv(cal.K))
    f = cal.apply_field(np.asarray(track.mag, float), {c: cov[c] for c in channels}) @ U
    return 10.0 * f if kind == "ardupilot" else f / 100.0


def _angle_deg(f: np.ndarray, h: np.ndarray) -> np.ndarray:
    cos = np.sum(f * h, axis=1) / np.linalg.norm(f, axis=1) / np.linalg.norm(h, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _horizontal(f: np.ndarray, up: np.ndarray) -> np.ndarray:
    h = f - np.sum(f * up, axis=1)[:, None] * up
    return h / np.linalg.norm(h, axis=1, keepdims=True)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
def test_motor_term_from_one_flight_corrects_another_with_the_firmware_formula(kind, tmp_path):
    suffix = ".bin" if kind == "ardupilot" else ".ulg"
    first, second = tmp_path / f"first{suffix}", tmp_path / f"second{suffix}"
    _write(kind, first, flight_slice(120.0, 1, motor_uT=MOTOR_UT))
    flight = flight_slice(120.0, 2, motor_uT=MOTOR_UT)
    _write(kind, second, flight)
    cal, parm = tmp_path / "new.json", tmp_path / f"new.{kind}"
    assert main(["fit", str(first), "--cal", "autopilot", "--add", "aux_interference",
                 "-o", str(cal)]) == 0
    assert main(["export", str(cal), "--format", kind, "-o", str(parm)]) == 0
    new = read_parameters(parm.read_text(), kind)
    motor = ("COMPASS_MOT_X", "COMPASS_MOTCT") if kind == "ardupilot" else \
        ("CAL_MAG0_XCOMP", "CAL_MAG_COMP_TYP")
    assert all(name in new for name in motor) and new[motor[1]] == 1   # throttle-based
    old = ardupilot_params() if kind == "ardupilot" else px4_params()

    track = read_recording(second)
    before = _corrected(kind, old, track, False)
    after = _corrected(kind, new, track, True)
    # the same flight without the motor field, corrected exactly: the reference direction
    clean = flight_slice(120.0, 2, motor_uT=0.0)
    reference = apply_ardupilot(old, 10.0 * clean.mag_uT) if kind == "ardupilot" else \
        apply_px4(old, clean.mag_uT / 100.0)
    g = np.column_stack([np.interp(flight.t_mag, flight.t_imu, flight.accel[:, k])
                         for k in range(3)])
    up = g / np.linalg.norm(g, axis=1, keepdims=True)

    def spread(f):
        norm = np.linalg.norm(f, axis=1)
        return float(np.std(norm) / np.mean(norm))

    def heading_rms(f):
        cos = np.sum(_horizontal(f, up) * _horizontal(reference, up), axis=1)
        return float(np.sqrt(np.mean(np.degrees(np.arccos(np.clip(cos, -1, 1))) ** 2)))

    # the firmware's formula with the exported parameters is streamcal's own correction: a
    # channel the firmware cannot take (the ArduPilot log's battery voltage) held at its level
    own = _own(Calibration.load(cal), track, kind)
    assert np.percentile(_angle_deg(after, own), 95) < 0.1
    assert len(track.mag) == len(reference)
    assert spread(after) < 0.6 * spread(before)
    assert spread(after) < 1.3 * spread(reference)          # down to what the sensor gives
    assert heading_rms(after) < 0.4 * heading_rms(before)


def test_cal_refit_on_the_channel_named(tmp_path, capsys):
    """``--add aux_interference=CHANNEL`` with ``--cal``: the motor term on that channel alone
    (a log with throttle, four motor outputs, battery current and voltage, which move together);
    a channel the log lacks, or beside a bare ``--add aux_interference``, is refused (exit 2)."""
    log = write_dataflash(tmp_path / "flight.bin", flight_slice(60.0, 1, motor_uT=MOTOR_UT))
    cal = tmp_path / "new.json"
    assert main(["fit", str(log), "--cal", "autopilot", "--add", "aux_interference=throttle",
                 "-o", str(cal)]) == 0
    fitted = Calibration.load(cal)
    g = np.array(fitted.effects["aux_interference"]["channels"]["throttle"]["g"])
    assert list(fitted.effects["aux_interference"]["channels"]) == ["throttle"]
    # the self-made field: MOTOR_UT over the flight's throttle span along one direction
    span = np.ptp(flight_slice(60.0, 1).throttle_at_mag)
    assert np.linalg.norm(g) == pytest.approx(MOTOR_UT / span, rel=0.1)
    capsys.readouterr()
    for add in (["aux_interference=rpm"], ["aux_interference", "aux_interference=throttle"]):
        args = [a for item in add for a in ("--add", item)]
        assert main(["fit", str(log), "--cal", "autopilot", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "aux_interference" in err


def test_motor_term_in_force_is_fitted_afresh(tmp_path):
    """A log whose autopilot already compensates the throttle (COMPASS_MOTCT 1, a wrong
    COMPASS_MOT): ``--add aux_interference`` fits the term again instead of keeping the one in
    force; the result is the term fitted from the same flight without compensation in force."""
    flight = flight_slice(60.0, 1, motor_uT=MOTOR_UT)
    fitted = {}
    for name, comp in (("none", None), ("wrong", np.array([-5.0, 3.0, -8.0]))):
        log = write_dataflash(tmp_path / f"{name}.bin", flight, messages=("IMU", "CURR"),
                              motor_comp=comp)
        cal = tmp_path / f"{name}.json"
        assert main(["fit", str(log), "--cal", "autopilot", "--add", "aux_interference=throttle",
                     "-o", str(cal)]) == 0
        fitted[name] = Calibration.load(cal)
    g = {k: np.array(c.effects["aux_interference"]["channels"]["throttle"]["g"])
         for k, c in fitted.items()}
    # the wrong term in force is 0.5–0.8 µT per throttle unit; the field is ~8 µT per unit
    assert np.linalg.norm(g["wrong"] - g["none"]) < 0.02 * np.linalg.norm(g["none"])
    assert fitted["wrong"].rms == pytest.approx(fitted["none"].rms, rel=0.02)
