"""Motor compensation checked on samples it was not fitted on (issue #24 item 4): a flight split
in time, the motor term fitted on one part against the calibration in force, exported, and
applied with ArduPilot's and PX4's own formulas to the other part
(:func:`streamcal.export.motor_check.held_out_check`). On a simulated flight with attitude and
GPS (battery current: COMPASS_MOTCT 2, PX4's kA), on a self-made DataFlash log (throttle), and on
the real ArduPilot logs (throttle; the PXF vehicle's motor field is large, the 2014 copter's
small)."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.errors import InputError
from streamcal.export.motor_check import held_out_check, split_in_time
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.inputs.autopilot_cal import calibration_from_ardupilot
from streamcal.sim.flight import simulated_log

from ._selfmade_logs import flight_slice, write_dataflash

S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])
GAIN = np.array([0.2, -0.1, 0.3])     # µT/A in the body frame: 1..13 µT over 5..35 A


def _firmwares_agree(out: dict, own: bool = True) -> None:
    """ArduPilot's and PX4's formulas give the same figures (one correction, two unit systems);
    with ``own`` also streamcal's own correction of the refined calibration."""
    for name in ("before", "refit", "after"):
        ap, px4 = out[name]["ardupilot"], out[name]["px4"]
        assert ap.keys() == px4.keys()
        for key in ap:
            assert px4[key] == pytest.approx(ap[key], abs=2e-3), (name, key)
    if own:
        for key, value in out["streamcal"].items():
            assert out["after"]["ardupilot"][key] == pytest.approx(value, abs=2e-3), key


def _in_force_without_motor_term(field_uT: float):
    """COMPASS_* that correct the simulated compass exactly but for its motor field."""
    S_ap = np.linalg.inv(S_TRUE)
    params = {f"COMPASS_OFS_{a}": -10.0 * B_TRUE[k] for k, a in enumerate("XYZ")}
    params.update({f"COMPASS_DIA_{a}": S_ap[k, k] for k, a in enumerate("XYZ")})
    params.update(COMPASS_ODI_X=S_ap[0, 1], COMPASS_ODI_Y=S_ap[0, 2], COMPASS_ODI_Z=S_ap[1, 2])
    return calibration_from_ardupilot(params, field_uT, source="simulated COMPASS_*")


@pytest.mark.parametrize("fit_on", ["first", "last"])
def test_current_term_from_one_half_corrects_the_other(fit_on):
    track, truth = simulated_log("flight", S=S_TRUE, b_body=B_TRUE, current_gain=GAIN, seed=5)
    cal = _in_force_without_motor_term(float(np.linalg.norm(truth["b_ned"])))
    out = held_out_check(track, cal, "battery_current_a", fit_on=fit_on)
    assert out["n_checked"] == 600 and "heading" not in out
    assert np.abs(np.array(out["g_uT"]) - GAIN).max() < 0.02
    _firmwares_agree(out)
    before, after = out["before"]["ardupilot"], out["after"]["ardupilot"]
    # 0.3 µT noise on a ~21 µT horizontal field: ~0.8° of heading noise is the floor
    assert after["heading_rms_deg"] < 1.0 < 5.0 < before["heading_rms_deg"]
    assert after["spread_pct"] < 0.15 * before["spread_pct"]
    # the refit without a motor term does not do it: the term is what corrects
    assert out["refit"]["ardupilot"]["spread_pct"] > 5 * after["spread_pct"]


def test_throttle_term_held_out_on_a_selfmade_dataflash_log(tmp_path):
    """A log without attitude or GPS: the spread is checked, the heading says why not."""
    path = write_dataflash(tmp_path / "flight.bin", flight_slice(120.0, 1, motor_uT=4.0),
                           messages=("IMU", "CURR"))
    track = read_recording(path)
    out = held_out_check(track, autopilot_calibration(track), "throttle")
    assert "GPS" in out["heading"] or "attitude" in out["heading"]
    _firmwares_agree(out)
    before, after = out["before"]["ardupilot"], out["after"]["ardupilot"]
    # 4 µT over the throttle range on a 48 µT field: ~2 % of spread, the sensor's own ~0.8 %
    assert after["spread_pct"] < 0.6 * before["spread_pct"]
    assert after["spread_pct"] < out["refit"]["ardupilot"]["spread_pct"]


def test_split_and_bad_channel():
    track, _ = simulated_log("flight", duration_s=20, current_gain=GAIN)
    first, rest = split_in_time(track, 0.25)
    assert len(first.t_mag) == 50 and len(rest.t_mag) == 150
    assert first.t_mag[-1] < rest.t_mag[0]
    with pytest.raises(InputError, match="neither a throttle"):
        held_out_check(track, None, "rcou_c1")
    with pytest.raises(InputError, match="no channel 'throttle'"):
        held_out_check(track, None, "throttle")


@pytest.mark.slow
@pytest.mark.parametrize("fit_on", ["first", "last"])
def test_real_pxf_throttle_term_held_out(flight_dir, fit_on):
    """The PXF copter (ArduPilot 3.4, COMPASS_MOTCT 0, no GPS): a throttle term fitted on one
    part lowers the field-magnitude spread of the other below the same refit without it
    (measured: std 23.3 → 18.6 % fitted on the first 890 s, 23.5 → 19.8 % on the rest)."""
    track = read_recording(flight_dir / "ardupilot_erle_PXFv2.0b_Rpi.BIN")
    out = held_out_check(track, autopilot_calibration(track), "throttle", fit_on=fit_on)
    assert "GPS" in out["heading"]
    _firmwares_agree(out)
    refit, after = out["refit"]["ardupilot"], out["after"]["ardupilot"]
    assert after["spread_pct"] < 0.9 * refit["spread_pct"]
    assert after["spread_robust_pct"] < refit["spread_robust_pct"]
    assert after["spread_pct"] < out["before"]["ardupilot"]["spread_pct"]


@pytest.mark.slow
def test_real_2014_copter_heading_held_out(flight_dir):
    """The 2014 copter (GPS, attitude): its motor field is small; the check gives the heading
    error against the attitude reference, and with the iron held (the first half determines
    only b_z) the firmwares' formulas are streamcal's own correction."""
    track = read_recording(flight_dir / "ardupilot_erle_15-12-2014_16.BIN")
    out = held_out_check(track, autopilot_calibration(track), "throttle")
    assert "heading" not in out
    _firmwares_agree(out)
    for name in ("before", "refit", "after"):
        figures = out[name]["ardupilot"]
        assert 0.0 < figures["heading_p95_deg"] < 20.0 and 0.0 < figures["spread_pct"] < 10.0
    assert np.linalg.norm(out["g_uT"]) < 5.0     # µT at full throttle: a small motor field


def test_wrong_motor_term_in_force_is_replaced(tmp_path):
    """COMPASS_MOTCT 1 with a wrong COMPASS_MOT in force: ``before`` applies it (the firmware's
    correction as flown), ``refit`` keeps it, ``after`` fits the term afresh and corrects."""
    path = write_dataflash(tmp_path / "flight.bin", flight_slice(120.0, 1, motor_uT=4.0),
                           messages=("IMU", "CURR", "BAT"),
                           motor_comp=np.array([-5.0, 3.0, -8.0]))
    track = read_recording(path)
    cal = autopilot_calibration(track)
    out = held_out_check(track, cal, "throttle")
    _firmwares_agree(out)
    before, after = out["before"]["ardupilot"], out["after"]["ardupilot"]
    assert after["spread_pct"] < 0.6 * before["spread_pct"]
    assert after["spread_pct"] < 0.6 * out["refit"]["ardupilot"]["spread_pct"]
    with pytest.raises(InputError, match="compensates throttle"):
        held_out_check(track, cal, "battery_current_a")
