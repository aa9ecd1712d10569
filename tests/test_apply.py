"""streamcal apply: calibrated field magnitude constant on a simulated track; heading checked
on known attitudes in two body-frame conventions."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.export.apply import apply_calibration, tilt_heading
from streamcal.sim import simulate


def test_apply_cli_constant_magnitude(tmp_path, capsys):
    sim = simulate(duration_s=40.0, seed=4, motor=False, field_uT=48.0)
    track_path, cal_path, out = tmp_path / "t.csv", tmp_path / "cal.json", tmp_path / "out.csv"
    sim.track.write(track_path)
    Calibration(K=sim.truth.K, b=sim.truth.b, field=48.0, n=1).save(cal_path)
    assert main(["apply", str(cal_path), str(track_path), "-o", str(out)]) == 0
    lines = out.read_text().splitlines()
    header = next(line for line in lines if not line.startswith("#"))
    assert header == "t,fx_uT,fy_uT,fz_uT,ux,uy,uz,heading_deg"
    data = np.loadtxt(out, delimiter=",", skiprows=lines.index(header) + 1)
    norm = np.linalg.norm(data[:, 1:4], axis=1)
    assert len(data) == len(sim.track.t_mag)
    assert abs(np.median(norm) - 48.0) < 0.5 and np.std(norm) < 1.0
    np.testing.assert_allclose(np.linalg.norm(data[:, 4:7], axis=1), 1.0, atol=1e-6)
    assert np.all((data[:, 7] >= 0) & (data[:, 7] < 360))


def test_apply_without_field_strength_says_so(tmp_path, capsys):
    sim = simulate(duration_s=10.0, seed=2, motor=False)
    track_path, cal_path, out = tmp_path / "t.csv", tmp_path / "cal.json", tmp_path / "out.csv"
    sim.track.write(track_path)
    Calibration(K=sim.truth.K, b=sim.truth.b, n=1).save(cal_path)
    assert main(["apply", str(cal_path), str(track_path), "-o", str(out)]) == 0
    assert "no field strength" in capsys.readouterr().err
    assert "|B| unknown" in out.read_text()


def _field_and_accel(rot_body_to_world, dip_deg=60.0):
    """ENU world: field north and down by ``dip``; specific force at rest points up."""
    dip = np.radians(dip_deg)
    field_world = 48.0 * np.array([0.0, np.cos(dip), -np.sin(dip)])
    return rot_body_to_world.inv().apply(field_world), rot_body_to_world.inv().apply([0, 0, 9.8])


def test_heading_flu_body_with_tilt():
    rng = np.random.default_rng(1)
    yaw = rng.uniform(0, 360, 200)                     # clockwise from north
    tilt = rng.uniform(-30, 30, (200, 2))
    # FLU body (x forward, z up) in ENU: heading ψ means body x = (sin ψ, cos ψ, 0) before tilt
    rot = Rotation.from_euler("ZYX", np.column_stack([90.0 - yaw, tilt]), degrees=True)
    field, accel = _field_and_accel(rot)
    heading = tilt_heading(field, accel)
    x_world = rot.apply([1.0, 0.0, 0.0])
    expected = np.degrees(np.arctan2(x_world[:, 0], x_world[:, 1])) % 360
    diff = (heading - expected + 180) % 360 - 180
    assert np.max(np.abs(diff)) < 1e-9


def test_heading_frd_body_level():
    """ArduPilot/PX4 body (x forward, y right, z down): at rest the accelerometer reads −g z."""
    yaw = np.radians(np.array([0.0, 45.0, 90.0, 200.0]))
    bh, bz = 20.0, 40.0   # horizontal and downward field, µT
    field = np.column_stack([bh * np.cos(yaw), -bh * np.sin(yaw), np.full(4, bz)])
    accel = np.tile([0.0, 0.0, -9.8], (4, 1))
    np.testing.assert_allclose(tilt_heading(field, accel), [0.0, 45.0, 90.0, 200.0], atol=1e-9)


def test_apply_nan_accel_rows_have_no_heading():
    cal = Calibration(K=np.eye(3) * 50, b=np.zeros(3), field=50.0, n=1)
    m = np.array([[50.0, 0, 0], [0, 50.0, 0]])
    accel = np.array([[0, 0, 9.8], [np.nan, np.nan, np.nan]])
    out = apply_calibration(cal, [0.0, 0.1], m, None, accel)
    assert np.isfinite(out.heading_deg[0]) and np.isnan(out.heading_deg[1])


def _applied(rows: int, heading: bool):
    from streamcal.export.apply import Applied

    rng = np.random.default_rng(3)
    values = rng.standard_normal((rows, 8)) * 10.0 ** rng.integers(-12, 12, (rows, 8))
    if rows:
        values[0, :3] = (np.nan, np.inf, -np.inf)
        values[-1, 3:] = (0.0, -0.0, 1e300, -1e-300, np.nan)
    return Applied(values[:, 0], values[:, 1:4], values[:, 4:7],
                   values[:, 7] if heading else None, 48.0, True, "uT")


@pytest.mark.parametrize("rows,heading", [(0, True), (1, False), (257, True), (1000, False),
                                          (4096, True), (9000, False)])
def test_format_body_is_savetxt_text(rows, heading):
    """The data lines are exactly what np.savetxt(fmt="%.9g", delimiter=",") writes, NaN → empty
    cell (the output format of earlier versions)."""
    import io

    from streamcal.export.apply import applied_columns, format_body

    applied = _applied(rows, heading)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(list(applied_columns(applied).values())), delimiter=",",
               fmt="%.9g")
    assert format_body(applied) == buf.getvalue().replace("nan", "")


def test_format_body_leaves_no_reference_cycle():
    """A chunk's text must be freed when the chunk is written, not at the next cyclic garbage
    collection (np.savetxt's file wrapper is a reference cycle holding the whole text)."""
    import gc

    from streamcal.export.apply import format_body

    applied = _applied(100, True)
    gc.collect()
    was = gc.isenabled()
    gc.disable()
    try:
        format_body(applied)
        assert gc.collect() == 0
    finally:
        if was:
            gc.enable()
