"""Export: each destination's documented correction, applied to raw readings, gives the same
field magnitude as streamcal's own Calibration.apply; the c-header keeps its exact format."""
import json
import re

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.export import export
from streamcal.export.ardupilot import apply_ardupilot
from streamcal.export.common import polar
from streamcal.export.px4 import apply_px4
from streamcal.sim import simulate

FIELD = 48.0


@pytest.fixture(scope="module")
def sim():
    return simulate(duration_s=60.0, seed=3, motor=False, field_uT=FIELD)


def _cal(truth, **kw):
    return Calibration(K=truth.K, b=truth.b, field=FIELD, n=100, **kw)


def _ardupilot_params(text):
    return {name: float(value) for name, value in
            (line.split(",") for line in text.splitlines() if line and not line.startswith("#"))}


def _px4_params(text):
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    return {r[2]: float(r[3]) for r in rows}


def test_polar_decomposition():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    U, S = polar(A)
    np.testing.assert_allclose(U @ S, A, atol=1e-12)
    np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(S, S.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(S) > 0)


def test_ardupilot_correction_matches_streamcal(sim):
    cal = _cal(sim.truth)
    assert abs(cal.K[0, 1]) > 0.1  # a real soft-iron term, so ODI is exercised
    text, notes = export(cal, "ardupilot")
    params = _ardupilot_params(text)
    assert params["COMPASS_ODI_X"] != 0 and "COMPASS_MOTCT" not in params
    m = sim.track.mag
    ours = np.linalg.norm(cal.apply_field(m), axis=1)
    theirs = np.linalg.norm(apply_ardupilot(params, m * 10.0), axis=1) / 10.0  # mG → µT
    np.testing.assert_allclose(theirs, ours, rtol=2e-6)
    raw = np.linalg.norm(m - m.mean(axis=0), axis=1)
    assert np.std(theirs) < 0.1 * np.std(raw)  # the correction does flatten the magnitude
    np.testing.assert_allclose(np.median(theirs), FIELD, rtol=0.02)
    np.testing.assert_allclose([params[f"COMPASS_OFS_{a}"] for a in "XYZ"],
                               -10.0 * sim.truth.b, rtol=1e-6)


def test_px4_correction_matches_streamcal(sim):
    cal = _cal(sim.truth)
    text, _ = export(cal, "px4")
    params = _px4_params(text)
    m = sim.track.mag
    ours = np.linalg.norm(cal.apply_field(m), axis=1)
    theirs = np.linalg.norm(apply_px4(params, m / 100.0), axis=1) * 100.0  # G → µT
    np.testing.assert_allclose(theirs, ours, rtol=2e-6)
    np.testing.assert_allclose([params[f"CAL_MAG0_{a}OFF"] for a in "XYZ"], sim.truth.b / 100,
                               rtol=1e-6)


def test_ardupilot_motor_compensation_from_aux_interference():
    """m = K x + b + g (a − a0): ArduPilot's S(r + ofs) + MOT·a must give a constant |f|."""
    rng = np.random.default_rng(5)
    K = np.array([[50.0, 2.0, -1.5], [0.0, 46.0, 3.0], [0.0, 0.0, 52.0]])
    b = np.array([12.0, -30.0, 8.0])
    g, a0 = np.array([0.8, -0.5, 1.2]), 3.0
    x = rng.normal(size=(2000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    current = rng.uniform(0.0, 20.0, 2000)
    m = x @ K.T + b + np.outer(current - a0, g)
    cal = Calibration(K=K, b=b, field=FIELD, n=2000,
                      model=("hard_iron", "soft_iron", "aux_interference"),
                      effects={"aux_interference": {"channels": {
                          "battery_current_a": {"a0": a0, "g": g.tolist()}}}})
    text, notes = export(cal, "ardupilot")
    params = _ardupilot_params(text)
    assert params["COMPASS_MOTCT"] == 2 and not notes
    f = apply_ardupilot(params, m * 10.0, current) / 10.0
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), FIELD, rtol=1e-5)
    without = apply_ardupilot(dict(params, COMPASS_MOTCT=0), m * 10.0, current) / 10.0
    assert np.std(np.linalg.norm(without, axis=1)) > 1.0  # the motor term matters here


def _aux_case(channel, a, g, a0, seed=5):
    """Readings m = K x + b + g (a − a0) and the Calibration that models them."""
    rng = np.random.default_rng(seed)
    K = np.array([[50.0, 2.0, -1.5], [0.0, 46.0, 3.0], [0.0, 0.0, 52.0]])
    b = np.array([12.0, -30.0, 8.0])
    x = rng.normal(size=(len(a), 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    m = x @ K.T + b + np.outer(a - a0, g)
    cal = Calibration(K=K, b=b, field=FIELD, n=len(a),
                      model=("hard_iron", "soft_iron", "aux_interference"),
                      effects={"aux_interference": {"channels": {
                          channel: {"a0": a0, "g": list(g)}}}})
    return m, cal


@pytest.mark.parametrize("channel, comp_type, to_power", [
    ("battery_current_a", 2, lambda a: a / 1000.0),  # PX4's power signal: A × 0.001 = kA
    ("throttle", 1, lambda a: a),                     # throttle 0..1 as it is
])
def test_px4_power_compensation_from_aux_interference(channel, comp_type, to_power):
    """PX4's f = S (r + p·COMP − OFF) with p its power signal gives the constant |f| of
    streamcal's model; without COMP the magnitude varies with the channel."""
    rng = np.random.default_rng(7)
    a = rng.uniform(0.0, 20.0, 2000) if comp_type == 2 else rng.uniform(0.0, 1.0, 2000)
    g = np.array([0.8, -0.5, 1.2]) * (1.0 if comp_type == 2 else 15.0)  # µT/A, µT/throttle
    m, cal = _aux_case(channel, a, g, a0=float(np.median(a)))
    text, notes = export(cal, "px4")
    params = _px4_params(text)
    assert not notes and "NOT EXPRESSED" not in text
    assert params["CAL_MAG_COMP_TYP"] == comp_type
    comp = np.array([params[f"CAL_MAG0_{ax}COMP"] for ax in "XYZ"])
    # unit and sign: G/kA = 10 × µT/A, G = µT/100, negated (PX4 adds it to the raw reading)
    np.testing.assert_allclose(comp, -g * (10.0 if comp_type == 2 else 0.01), rtol=1e-6)
    theirs = np.linalg.norm(apply_px4(params, m / 100.0, to_power(a)), axis=1) * 100.0
    ours = np.linalg.norm(cal.apply_field(m, {channel: a}), axis=1)
    np.testing.assert_allclose(ours, FIELD, rtol=1e-6)
    np.testing.assert_allclose(theirs, ours, rtol=2e-6)
    without = np.linalg.norm(apply_px4(dict(params, CAL_MAG_COMP_TYP=0), m / 100.0,
                                       to_power(a)), axis=1) * 100.0
    assert np.std(without) > 1.0  # the power term matters here
    flipped = np.linalg.norm(apply_px4(params, m / 100.0, -to_power(a)), axis=1) * 100.0
    assert np.std(flipped) > np.std(without)  # the wrong sign makes it worse


@pytest.mark.parametrize("firmware", ["ardupilot", "px4"])
def test_channel_not_exported_is_held_at_its_level(firmware):
    """A fitted channel the autopilot cannot compensate (battery voltage beside the throttle)
    is held at its level a0: the firmware's formula gives streamcal's own corrected field
    vector with that channel at a0 (in the symmetric frame), not with it at 0 V."""
    rng = np.random.default_rng(11)
    throttle, volts = rng.uniform(0.3, 0.9, 2000), rng.uniform(11.0, 12.6, 2000)
    g_thr, g_volt, a0_volt = np.array([4.7, -2.7, 6.0]), np.array([-0.4, 0.1, -0.2]), 11.8
    m, cal = _aux_case("throttle", throttle, g_thr, a0=0.6)
    cal.effects["aux_interference"]["channels"]["battery_voltage_v"] = {
        "a0": a0_volt, "g": g_volt.tolist()}
    m = m + np.outer(volts - a0_volt, g_volt)
    text, notes = export(cal, firmware)
    assert any("battery_voltage_v" in n and "a0" in n for n in notes)
    # and the exported term alone is said not to be the joint fit's correction
    assert any("fitted together" in n and "--add aux_interference=throttle" in n for n in notes)
    held = {"throttle": throttle, "battery_voltage_v": np.full(len(m), a0_volt)}
    U, _ = polar(FIELD * np.linalg.inv(cal.K))
    ours = cal.apply_field(m, held) @ U         # Uᵀ f: the symmetric matrix's frame, µT
    if firmware == "ardupilot":
        theirs = apply_ardupilot(_ardupilot_params(text), m * 10.0, throttle) / 10.0
    else:
        theirs = apply_px4(_px4_params(text), m / 100.0, throttle) * 100.0
    np.testing.assert_allclose(theirs, ours, atol=2e-4)
    # the voltage's swing is all that is left: |f| within |g_volt| × its half-range of FIELD
    swing = np.linalg.norm(g_volt) * np.max(np.abs(volts - a0_volt))
    assert np.max(np.abs(np.linalg.norm(theirs, axis=1) - FIELD)) < 1.05 * swing


def test_second_battery_is_px4_type_3_and_not_ardupilot():
    """A term on the second battery's current: PX4's CAL_MAG_COMP_TYP 3 (battery_status
    instance 1, kA) corrects it exactly; ArduPilot's COMPASS_MOTCT 2 takes the first battery
    only, so it is not expressed there."""
    rng = np.random.default_rng(9)
    a = rng.uniform(5.0, 30.0, 2000)
    m, cal = _aux_case("battery2_current_a", a, np.array([0.3, -0.2, 0.4]), a0=15.0)
    text, notes = export(cal, "px4")
    params = _px4_params(text)
    assert not notes and params["CAL_MAG_COMP_TYP"] == 3
    theirs = np.linalg.norm(apply_px4(params, m / 100.0, a / 1000.0), axis=1) * 100.0
    np.testing.assert_allclose(theirs, FIELD, rtol=2e-6)
    text, notes = export(cal, "ardupilot")
    assert any("battery2_current_a" in n for n in notes)
    assert "COMPASS_MOTCT" not in _ardupilot_params(text)


def test_px4_second_or_unknown_channel_not_expressed():
    a = np.linspace(0.0, 1.0, 200)
    _, cal = _aux_case("motor_rpm", a, np.array([1.0, 0.0, 0.0]), a0=0.5)
    text, notes = export(cal, "px4")
    assert any("motor_rpm" in n for n in notes) and "NOT EXPRESSED" in text
    assert "CAL_MAG_COMP_TYP" not in _px4_params(text)


def test_c_header_exact_format(sim):
    cal = _cal(sim.truth)
    text, _ = export(cal, "c-header")
    assert "#ifndef SC_INITIAL_CAL_H\n#define SC_INITIAL_CAL_H\n" in text
    k = re.search(r"#define SC_INITIAL_CAL_K \{([^}]*)\}", text).group(1).split(", ")
    b = re.search(r"#define SC_INITIAL_CAL_B \{([^}]*)\}", text).group(1).split(", ")
    assert len(k) == 6 and len(b) == 3 and all(v.endswith("f") for v in k + b)
    K = cal.K
    np.testing.assert_allclose([float(v[:-1]) for v in k],
                               [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], K[2, 2]], rtol=1e-8)
    np.testing.assert_allclose([float(v[:-1]) for v in b], cal.b, rtol=1e-8)


def test_json_is_the_calibration_file(sim):
    cal = _cal(sim.truth)
    text, notes = export(cal, "json")
    back = Calibration.from_json(text)
    np.testing.assert_array_equal(back.K, cal.K)
    assert back.field == FIELD and not notes


def test_cli_export_says_what_is_not_expressed(sim, tmp_path, capsys):
    cal = _cal(sim.truth, model=("hard_iron", "soft_iron", "temperature_offset"),
               effects={"temperature_offset": {"T0": 25.0, "c": [0.1, -0.2, 0.05]}})
    path = tmp_path / "cal.json"
    cal.save(path)
    for fmt in ("ardupilot", "px4", "c-header"):
        out = tmp_path / f"out.{fmt}"
        assert main(["export", str(path), "--format", fmt, "-o", str(out)]) == 0
        err = capsys.readouterr().err
        assert "temperature_offset" in err and "cannot express" in err
        assert "NOT EXPRESSED: temperature_offset" in out.read_text()
    assert main(["export", str(path), "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out)["effects"]["temperature_offset"]["T0"] == 25.0
    assert main(["export", str(tmp_path / "missing.json"), "--format", "px4"]) == 2


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_parameter_files_are_ascii(sim, tmp_path, monkeypatch, fmt):
    """Comments in parameter files are plain ASCII ("uT/degC", not "µT/°C"): MAVProxy's
    ``param load`` reads the file in the platform's encoding, which may be ASCII (a POSIX
    locale) or a code page; the values read back are those written."""
    import builtins

    from pymavlink import mavparm

    cal = _cal(sim.truth, model=("hard_iron", "soft_iron", "temperature_offset"),
               effects={"temperature_offset": {"T0": 25.0, "c": [0.1, -0.2, 0.05]}})
    path = tmp_path / "cal.json"
    cal.save(path)
    out = tmp_path / f"out.{fmt}"
    assert main(["export", str(path), "--format", fmt, "-o", str(out)]) == 0
    raw = out.read_bytes()
    assert raw.isascii()
    text = raw.decode("ascii")
    assert "T0 25 degC, c [0.1, -0.2, 0.05] uT/degC" in text
    want = (_ardupilot_params if fmt == "ardupilot" else _px4_params)(text)
    assert want == (_ardupilot_params if fmt == "ardupilot" else _px4_params)(
        export(cal, fmt)[0])
    if fmt == "ardupilot":
        monkeypatch.setattr(mavparm, "open", lambda f, mode="r": builtins.open(
            f, mode, encoding="ascii"), raising=False)
        loaded = mavparm.MAVParmDict()
        assert loaded.load(str(out))
        assert {k: loaded[k] for k in want} == pytest.approx(want)
