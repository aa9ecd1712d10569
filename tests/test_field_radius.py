"""The field strength of a held calibration (the ``radius`` of K): re-estimated where the model
determines it, so that a refinement of an autopilot's calibration in force — read with the
median size of its corrected field, which an uncompensated motor field inflates — fits the motor
term it is (docs/diagnose_against_calibration.md, "The field strength")."""
from __future__ import annotations

import json

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.diagnosis.against import refine
from streamcal.diagnosis.held.fit import jacobian, project
from streamcal.diagnosis.held.start import HeldStart
from streamcal.fitting.entries import RADIUS, entry, field_radius, shifted, with_entries
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.inputs.track import Track
from streamcal.sim import simulate
from streamcal.sim.flight import simulated_log

from ._selfmade_logs import px4_mounted_params
from .test_px4_rotated_compass import (B_BODY, GAIN, MOUNT, S_BODY, _exported_px4, _flight,
                                       _heading_rms, _px4_formula)

K0 = np.array([[50.0, 1.0, -2.0], [0.0, 47.0, 0.5], [0.0, 0.0, 52.0]])
B0 = np.array([3.0, -4.0, 5.0])


def test_radius_is_the_scale_of_the_whole_K():
    r = field_radius(K0)
    assert entry(K0, B0, RADIUS) == pytest.approx(np.prod(np.diag(K0)) ** (1 / 3))
    K, b = shifted(K0, B0, [RADIUS, "K_xx"], [0.1 * r, 2.0])
    assert K == pytest.approx(K0 * 1.1 + np.diag([2.0, 0, 0]))     # scaled, then shifted
    assert b == pytest.approx(B0)
    K, _ = with_entries(K0, B0, ["K_xy", RADIUS], [3.0, 40.0])     # the radius set first
    assert field_radius(K) == pytest.approx(40.0)
    assert K[0, 1] == pytest.approx(3.0) and K[1, 1] / K[2, 2] == pytest.approx(47.0 / 52.0)


def test_radius_column_is_the_derivative_of_the_normal_residual():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(200, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    m = u @ (K0 * 1.02).T + B0 + rng.normal(scale=0.2, size=(200, 3))
    _, x, s, normal, D = project(K0, B0, [], m, {})
    A = jacobian([RADIUS], [], x, normal, D, {}, x @ K0.T, K0)
    h = 1e-4
    K1, _ = shifted(K0, B0, [RADIUS], [h])
    _, _, s1, _, _ = project(K1, B0, [], m, {}, x, 50)
    assert (s1 - s) / h == pytest.approx(-A[:, 0], rel=2e-3, abs=1e-6)   # ds = −a dp


@pytest.fixture(scope="module")
def px4_flight(tmp_path_factory):
    """A self-made PX4 flight whose calibration in force is exact but for a battery-current
    motor field it does not compensate, refined with the motor term."""
    d = tmp_path_factory.mktemp("radius")
    path, params = _flight(d / "one.ulg", 0)
    new = d / "new.json"
    assert main(["fit", str(path), "--cal", "autopilot", "--add",
                 "aux_interference=battery_current_a", "-o", str(new)]) == 0
    return path, params, new


def test_the_motor_field_does_not_set_the_field_strength(px4_flight):
    path, params, new = px4_flight
    track = read_recording(path)
    in_force = autopilot_calibration(track)
    refined = Calibration.load(new)
    true_strength = float(np.linalg.norm(simulated_log("flight", duration_s=240, seed=0)[1]
                                         ["b_ned"]))
    assert abs(in_force.field - true_strength) > 0.05 * true_strength   # the median carries it
    assert refined.field == pytest.approx(true_strength, rel=0.005)
    assert "radius" not in refined.extra["held"]
    g = np.array(refined.effects["aux_interference"]["channels"]["battery_current_a"]["g"])
    assert g == pytest.approx(MOUNT.matrix.T @ GAIN, abs=0.02 * np.linalg.norm(GAIN))
    # the matrix an autopilot is given keeps the scale of the one in force
    exported = _exported_px4(refined)
    for name in ("CAL_MAG0_XSCALE", "CAL_MAG0_YSCALE", "CAL_MAG0_ZSCALE"):
        assert exported[name] == pytest.approx(params[name], rel=0.01)


def test_the_refined_heading_is_the_true_calibrations(px4_flight):
    path, params, new = px4_flight
    track = read_recording(path)
    true_params = px4_mounted_params(MOUNT.matrix, MOUNT.px4, S_BODY, B_BODY,
                                     comp_g_per_ka=-10.0 * MOUNT.matrix.T @ GAIN)
    noise = _heading_rms(track, lambda m, amps: _px4_formula(true_params, m, amps))
    check = json.loads(new.read_text())["heading_check"]
    assert check["rms_before"] > 10 * noise
    assert check["rms_after"] == pytest.approx(noise, abs=0.1)


def test_a_field_strength_that_differs_between_halves_is_held(px4_flight):
    """The second half of the flight scaled about the offset, as if flown where the field is
    2 % stronger (1 µT, several σ of the radius of each half): the radius is not one number, so
    the motor term does not release it (it would without the halves compared: 48.84 µT) and the
    refinement keeps the field strength in force."""
    path, _, _ = px4_flight
    read = read_recording(path)
    b = MOUNT.matrix.T @ B_BODY
    late = read.mag_rows & (read.columns["t"] >= np.median(read.t_mag))
    columns = dict(read.columns)
    for k, name in enumerate(("mx", "my", "mz")):
        col = np.array(columns[name])
        col[late] = b[k] + 1.02 * (col[late] - b[k])
        columns[name] = col
    track = Track(columns, read.metadata, read.path, read.lines)
    in_force = autopilot_calibration(track)
    refined = refine(track, in_force, ["aux_interference"])
    assert "radius" in refined.extra["held"]
    assert refined.field == pytest.approx(in_force.field)


def test_a_tumble_never_names_the_radius():
    """Where the diagonal of K is all re-estimated the radius would repeat it: not considered,
    not in the held list."""
    sim = simulate(120, seed=2)
    cal = Calibration(K=np.asarray(sim.truth.K, float) * 1.05, b=np.asarray(sim.truth.b, float),
                      unit="uT")
    start = HeldStart(sim.track, cal)
    assert {"K_xx", "K_yy", "K_zz"} <= set(start.free)
    assert RADIUS not in start.names and RADIUS not in start.free
