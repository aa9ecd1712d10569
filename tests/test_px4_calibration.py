"""PX4's CAL_MAGn_* as a streamcal Calibration (streamcal.inputs.calibration_from_px4), against
PX4's documented correction c = R S (r + p·comp − o) on synthetic readings."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.errors import InputError
from streamcal.inputs import calibration_from_px4

FIELD_UT = 48.0


def _px4_params(comp_type=0, comp=(0.0, 0.0, 0.0), prefix="CAL_MAG1_"):
    rng = np.random.default_rng(7)
    S = np.eye(3) + 0.08 * rng.standard_normal((3, 3))
    S = (S + S.T) / 2
    o = 0.3 * rng.standard_normal(3)
    params = {f"{prefix}{a}SCALE": S[k, k] for k, a in enumerate("XYZ")}
    params.update({f"{prefix}XODIAG": S[0, 1], f"{prefix}YODIAG": S[0, 2],
                   f"{prefix}ZODIAG": S[1, 2], "CAL_MAG_COMP_TYP": comp_type})
    params.update({f"{prefix}{a}OFF": o[k] for k, a in enumerate("XYZ")})
    params.update({f"{prefix}{a}COMP": comp[k] for k, a in enumerate("XYZ")})
    return params, S, o


def _raw_readings(S, o, comp=np.zeros(3), power=None, n=500):
    """Readings r (G) whose PX4 correction R S (r + p·comp − o) is the field at FIELD_UT, R a
    board rotation; returned as µT with the unit directions u."""
    rng = np.random.default_rng(3)
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    c = FIELD_UT / 100.0 * u
    p = np.zeros(n) if power is None else power
    r = np.linalg.solve(S, R.T @ c.T).T + o - p[:, None] * comp
    return 100.0 * r, u


def test_the_calibration_maps_raw_readings_onto_the_field_it_was_made_for():
    params, S, o = _px4_params()
    m, _ = _raw_readings(S, o)
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_")
    np.testing.assert_allclose(np.linalg.norm(cal.apply(m), axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(cal.b, 100.0 * o, rtol=1e-12)
    assert cal.model == ("hard_iron", "soft_iron") and cal.field == FIELD_UT
    assert "rotation R only turns the directions" in cal.extra["note"]



def test_the_rotation_puts_the_directions_in_the_body_frame():
    """With PX4's rotation R (the board rotation of :func:`_raw_readings`) the calibrated
    directions, turned by frame_rotation_Q, are PX4's corrected field R S (r − o): the body
    frame; K (the ellipsoid) is the same as without R."""
    from streamcal.fitting.attitude_reference import body_field

    params, S, o = _px4_params()
    m, u = _raw_readings(S, o)
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_", rotation=R)
    np.testing.assert_allclose(body_field(cal, m, {}), FIELD_UT * u, atol=1e-9)
    plain = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_")
    np.testing.assert_allclose(cal.K, plain.K, atol=1e-9)
    assert not np.allclose(body_field(plain, m, {}), FIELD_UT * u, atol=1e-3)

def test_battery_current_compensation_becomes_an_aux_interference_term():
    """CAL_MAG_COMP_TYP = 2: p is battery 0's current in kA; on raw readings (sensor_mag) the
    compensation is a term of the model on battery_current_a (A)."""
    comp = np.array([0.04, -0.02, 0.03])                  # G per kA
    params, S, o = _px4_params(comp_type=2, comp=comp)
    current_a = np.linspace(0.0, 40.0, 500)
    m, _ = _raw_readings(S, o, comp, power=current_a * 1e-3)
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_")
    assert "aux_interference" in cal.model
    x = cal.apply(m, {"battery_current_a": current_a})
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, rtol=1e-9)
    without = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_",
                                   compensation_in_readings=True)
    assert "aux_interference" not in without.model
    assert "already in the readings" in without.extra["note"]


def test_second_battery_compensation_is_a_term_on_its_current():
    """CAL_MAG_COMP_TYP = 3: p is battery_status instance 1's current in kA, streamcal's
    battery2_current_a (A)."""
    comp = np.array([0.04, -0.02, 0.03])                  # G per kA
    params, S, o = _px4_params(comp_type=3, comp=comp)
    current_a = np.linspace(0.0, 40.0, 500)
    m, _ = _raw_readings(S, o, comp, power=current_a * 1e-3)
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_",
                               channels=("battery_current_a", "battery2_current_a"))
    assert set(cal.effects["aux_interference"]["channels"]) == {"battery2_current_a"}
    x = cal.apply(m, {"battery2_current_a": current_a})
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, rtol=1e-9)


def test_throttle_compensation_is_a_term_on_the_throttle_channel():
    """CAL_MAG_COMP_TYP = 1: p is the throttle 0..1 (actuator_controls_0.control[3])."""
    comp = np.array([0.05, 0.01, -0.04])                  # G at full throttle
    params, S, o = _px4_params(comp_type=1, comp=comp)
    throttle = np.linspace(0.0, 0.8, 500)
    m, _ = _raw_readings(S, o, comp, power=throttle)
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_")
    assert set(cal.effects["aux_interference"]["channels"]) == {"throttle"}
    x = cal.apply(m, {"throttle": throttle})
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, rtol=1e-9)


@pytest.mark.parametrize("comp_type, channels, signal", [
    (1, ("battery_current_a",), "throttle"), (2, ("throttle",), "battery_current_a"),
    (3, ("throttle", "battery_current_a"), "battery2_current_a")])
def test_a_compensation_without_its_channel_is_left_out_and_said(comp_type, channels, signal):
    params, _, _ = _px4_params(comp_type=comp_type, comp=(0.01, 0.0, 0.0))
    cal = calibration_from_px4(params, FIELD_UT, prefix="CAL_MAG1_", channels=channels)
    assert "aux_interference" not in cal.model
    assert f"CAL_MAG_COMP_TYP={comp_type} left out: its signal ({signal})" in cal.extra["note"]


def test_missing_offsets_or_a_singular_matrix_are_refused():
    params, _, _ = _px4_params()
    with pytest.raises(InputError, match="no CAL_MAG1_YOFF parameter"):
        calibration_from_px4({k: v for k, v in params.items() if k != "CAL_MAG1_YOFF"},
                             FIELD_UT, prefix="CAL_MAG1_")
    singular = {**params, "CAL_MAG1_XSCALE": 0.0, "CAL_MAG1_XODIAG": 0.0,
                "CAL_MAG1_YODIAG": 0.0}
    with pytest.raises(InputError, match="singular"):
        calibration_from_px4(singular, FIELD_UT, prefix="CAL_MAG1_")
    with pytest.raises(InputError, match="positive number of µT"):
        calibration_from_px4(params, float("nan"), prefix="CAL_MAG1_")


def test_the_ulog_reader_takes_the_throttle_px4_compensates_with():
    """actuator_controls_0.control[3] becomes the ``throttle`` column when it moves; a constant
    one (a log on the ground: the bundled samples) is left out like every constant channel."""
    from types import SimpleNamespace

    from streamcal.inputs.ulog import _throttle

    def log(values):
        topic = SimpleNamespace(name="actuator_controls_0", multi_id=0,
                                data={"timestamp": np.arange(4) * 10_000,
                                      "control[3]": np.asarray(values, np.float32)})
        return SimpleNamespace(data_list=[topic])

    meta = {}
    stream = _throttle(log([0.0, 0.4, 0.55, 0.5]), meta)
    np.testing.assert_allclose(stream.columns["throttle"], [0.0, 0.4, 0.55, 0.5], rtol=1e-7)
    np.testing.assert_allclose(stream.t, [0.0, 0.01, 0.02, 0.03])
    assert meta["throttle_source"] == "actuator_controls_0.control[3] (0..1)"
    assert _throttle(log([0.0, 0.0, 0.0, 0.0]), {}) is None
