"""The physics simulator: determinism, the model identities, quantization, every effect's term,
coverage patterns, outlier spans, asynchronous rows and the paper's synthetic protocol."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.errors import InputError, UnknownEffectError
from streamcal.sim import paper_protocol, simulate
from streamcal.sim.motion import cumulative_rotation, hand_motion, smooth_noise
from streamcal.sim.sensor import ACCEL_LSB, GYRO_LSB, MAG_LSB_UT

DUR = 60.0
# Seeds of the shared base run and of the coverage runs.
SEED = 3


def _run(**kw):
    kw.setdefault("duration_s", DUR)
    kw.setdefault("seed", SEED)
    return simulate(**kw)


@pytest.fixture(scope="module")
def base():
    return _run()


@pytest.fixture(scope="module")
def bursty():
    return _run(outlier_bursts=3, seed=11)


def _corr(a, b):
    return np.corrcoef(a, b)[0, 1]


# ---------------------------------------------------------------- determinism, model identities

def test_deterministic_per_seed(base):
    again = _run()
    for name, col in base.track.columns.items():
        np.testing.assert_array_equal(col, again.track.columns[name], err_msg=name)
    other = _run(seed=SEED + 1)
    assert not np.array_equal(base.track.mag[:100], other.track.mag[:100])


def test_noise_free_readings_follow_the_model(base):
    tr = base.truth
    np.testing.assert_allclose(np.linalg.norm(tr.directions, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(tr.mag_clean, tr.directions @ tr.K.T + tr.b, atol=1e-10)
    assert np.all(np.tril(tr.K, -1) == 0) and np.all(np.diag(tr.K) > 0)
    # Without misalignment the magnetometer and body frames agree.
    np.testing.assert_allclose(tr.directions, tr.directions_body, atol=1e-12)


def test_field_magnitude_is_constant_after_inverting_the_truth(base):
    tr = base.truth
    x_clean = np.linalg.solve(tr.K, (tr.mag_clean - tr.b).T).T
    np.testing.assert_allclose(np.linalg.norm(x_clean, axis=1), 1.0, atol=1e-12)
    x = np.linalg.solve(tr.K, (base.track.mag - tr.b).T).T
    field = tr.field_uT * np.linalg.norm(x, axis=1)
    assert abs(field.mean() - tr.field_uT) < 0.05
    # Spread of |B| is the per-axis noise (plus quantization), not the soft/hard iron (tens of µT).
    assert 0.5 * tr.noise_uT < field.std() < 1.5 * tr.noise_uT


def test_measured_minus_clean_is_noise(base):
    res = base.track.mag - base.truth.mag_clean
    lsb = base.truth.mag_lsb
    np.testing.assert_allclose(res.std(axis=0), np.hypot(base.truth.noise_uT, lsb / np.sqrt(12)),
                               rtol=0.1)
    assert np.all(np.abs(res.mean(axis=0)) < 0.03)


@pytest.mark.parametrize("bits", [16, 14])
def test_quantization_step_is_visible(bits):
    res = _run(duration_s=20, mag_bits=bits)
    lsb = res.truth.mag_lsb
    counts = res.track.mag / lsb
    assert np.all(np.abs(counts - np.round(counts)) < 0.02)
    np.testing.assert_allclose(lsb / MAG_LSB_UT[bits], np.round(lsb / MAG_LSB_UT[bits] * 256) / 256,
                               atol=1e-12)  # fuse-ROM adjustment (ASA−128)/256 + 1
    steps = np.diff(np.unique(res.track.mag[:, 0]))
    assert steps.min() == pytest.approx(lsb[0], abs=2e-3)
    if bits == 14:
        assert lsb.min() > 0.6 and steps.min() > 0.5


def test_imu_quantization_and_gravity(base):
    tr = base.track
    for values, lsb in ((tr.accel, ACCEL_LSB), (tr.gyro, GYRO_LSB)):
        c = values / lsb
        assert np.all(np.abs(c - np.round(c)) < 0.1)
    assert abs(np.median(np.linalg.norm(tr.accel, axis=1)) - 9.80665) < 0.2


# ---------------------------------------------------------------- rows, files

def test_fast_imu_stamps_stay_increasing():
    res = _run(duration_s=3, imu_rate_hz=4000)
    t_imu = res.track.t[res.track.accel_rows]
    assert np.all(np.diff(t_imu) > 0) and abs(len(t_imu) - 12000) <= 1


def test_async_rows_have_empty_cells(base):
    tr = base.track
    cols = tr.columns
    mag_rows = tr.mag_rows
    imu_rows = np.isfinite(cols["ax"])
    assert not np.any(mag_rows & imu_rows) and np.all(mag_rows | imu_rows)
    for name in ("ax", "ay", "az", "gx", "gy", "gz", "temp", "motor_current"):
        assert np.all(np.isnan(cols[name][mag_rows])), name
        assert np.all(np.isfinite(cols[name][imu_rows])), name
    for name in ("mx", "my", "mz"):
        assert np.all(np.isnan(cols[name][imu_rows]))
    assert abs(mag_rows.sum() - 100 * DUR) <= 1 and abs(imu_rows.sum() - 200 * DUR) <= 1
    assert np.all(np.diff(tr.t) >= 0)
    dt = np.diff(tr.t_mag)
    assert 0 < dt.min() < 0.01 < dt.max() < 0.0105 and dt.std() > 1e-5  # jittered 100 Hz
    np.testing.assert_array_equal(tr.t_mag, base.truth.t_mag)


def test_write_and_read_back(base, tmp_path):
    from streamcal.inputs.track import Track
    path = tmp_path / "sim.csv.gz"
    base.write(path, truth_path=tmp_path / "truth.json")
    back = Track.read(path)
    for name, col in base.track.columns.items():
        np.testing.assert_allclose(back.columns[name], col, atol=1e-9, equal_nan=True, err_msg=name)
    assert back.metadata["simulated"] == "yes" and back.metadata["seed"] == str(SEED)
    import json
    truth = json.loads((tmp_path / "truth.json").read_text())
    np.testing.assert_allclose(truth["K"], base.truth.K)


def test_bad_arguments_are_named():
    with pytest.raises(UnknownEffectError, match="bogus"):
        simulate(duration_s=5, effects={"bogus": 1.0})
    with pytest.raises(InputError, match="hard_iron"):
        simulate(duration_s=5, effects={"hard_iron": 1.0})
    with pytest.raises(InputError, match="mag_bits"):
        simulate(duration_s=5, mag_bits=12)
    with pytest.raises(InputError, match="upper triangular"):
        simulate(duration_s=5, K=np.ones((3, 3)))


# ---------------------------------------------------------------- effects

def _pair(name, magnitude, **kw):
    """The same session without and with one effect (motion and noise streams are shared)."""
    return _run(duration_s=40, **kw), _run(duration_s=40, effects={name: magnitude}, **kw)


def test_temperature_offset_follows_temperature():
    off, on = _pair("temperature_offset", 0.3, temp_profile="cycle", temp_delta_c=10)
    tr = on.truth
    c = np.array(tr.effects["temperature_offset"]["c"])
    assert np.linalg.norm(c) == pytest.approx(0.3)
    np.testing.assert_allclose(tr.mag_clean - off.truth.mag_clean,
                               np.outer(tr.temp - 25.0, c), atol=1e-9)
    resid = (on.track.mag - (tr.directions @ tr.K.T + tr.b)) @ (c / np.linalg.norm(c))
    assert _corr(resid, tr.temp) > 0.9
    resid_off = (off.track.mag - (tr.directions @ tr.K.T + tr.b)) @ (c / np.linalg.norm(c))
    assert abs(_corr(resid_off, tr.temp)) < 0.1


def test_temperature_scale_changes_the_gain():
    off, on = _pair("temperature_scale", 0.002, temp_profile="ramp", temp_delta_c=15)
    tr = on.truth
    s = np.array(tr.effects["temperature_scale"]["s"])
    u = tr.directions @ tr.K.T
    np.testing.assert_allclose(tr.mag_clean - off.truth.mag_clean,
                               (tr.temp - 25.0)[:, None] * s * u, atol=1e-9)
    # Per-axis gain ratio |m − b| / |u| along the dominant axis follows 1 + s (T − T0).
    i = np.argmax(np.abs(s))
    big = np.abs(u[:, i]) > 30
    gain = (tr.mag_clean[big, i] - tr.b[i]) / u[big, i]
    np.testing.assert_allclose(gain, 1 + s[i] * (tr.temp[big] - 25.0), atol=1e-12)


def test_time_drift_follows_time():
    off, on = _pair("time_drift", 0.2)  # 8 µT over 40 s against 0.4 µT noise
    tr = on.truth
    d = np.array(tr.effects["time_drift"]["d"])
    np.testing.assert_allclose(tr.mag_clean - off.truth.mag_clean, np.outer(tr.t_sample, d),
                               atol=1e-9)
    resid = (on.track.mag - (tr.directions @ tr.K.T + tr.b)) @ (d / np.linalg.norm(d))
    assert _corr(resid, tr.t_mag) > 0.9


def test_aux_interference_follows_the_motor_current():
    off, on = _pair("aux_interference", 2.0)
    tr = on.truth
    g = np.array(tr.effects["aux_interference"]["channels"]["motor_current"]["g"])
    np.testing.assert_allclose(tr.mag_clean - off.truth.mag_clean, np.outer(tr.motor_current, g),
                               atol=1e-9)
    assert tr.motor_current.max() > 0.4 and tr.motor_current.min() == 0.0  # on/off segments
    resid = (on.track.mag - (tr.directions @ tr.K.T + tr.b)) @ (g / np.linalg.norm(g))
    assert _corr(resid, tr.motor_current) > 0.9
    # The recorded channel is the true current plus a little noise.
    current = on.track.covariates_at_mag()["motor_current"]
    assert np.abs(current - tr.motor_current).max() < 0.1


def test_axis_nonlinearity_is_cubic_in_the_undistorted_reading():
    off, on = _pair("axis_nonlinearity", 0.02)
    tr = on.truth
    p = tr.effects["axis_nonlinearity"]
    assert p["R"] == tr.field_uT
    u = tr.directions @ tr.K.T
    np.testing.assert_allclose(tr.mag_clean - off.truth.mag_clean,
                               np.array(p["a"]) * u ** 3 / tr.field_uT ** 2, atol=1e-9)
    # The inverted truth no longer gives a constant field magnitude.
    x = np.linalg.solve(tr.K, (tr.mag_clean - tr.b).T).T
    assert np.ptp(np.linalg.norm(x, axis=1)) > 0.005


def test_misalignment_breaks_the_constant_dip():
    off, on = _pair("mag_accel_misalignment", 0.05)
    p = on.truth.effects["mag_accel_misalignment"]
    R = Rotation.from_rotvec(p["rotation"])
    np.testing.assert_allclose(R.apply(on.truth.directions), on.truth.directions_body, atol=1e-12)

    def angle(x, up):
        return np.arccos(np.clip(np.sum(x * up, axis=1), -1, 1))

    expected = np.pi / 2 + np.radians(on.truth.dip_deg)  # field vs up, i.e. dip + 90°
    np.testing.assert_allclose(angle(off.truth.directions, off.truth.up_body), expected, atol=1e-9)
    np.testing.assert_allclose(np.pi - expected, p["dip"], atol=1e-12)  # field vs down
    seen = angle(on.truth.directions, on.truth.up_body)
    assert np.ptp(seen) > 0.05 and np.abs(seen - expected).max() <= 0.05 + 1e-9
    # Readings still satisfy m = K x + b in the magnetometer frame.
    np.testing.assert_allclose(on.truth.mag_clean, on.truth.directions @ on.truth.K.T + on.truth.b,
                               atol=1e-10)


def test_time_lag_shifts_the_samples():
    off, on = _pair("time_lag", 0.05)
    assert on.truth.effects["time_lag"]["tau"] == 0.05
    np.testing.assert_array_equal(on.track.t_mag, off.track.t_mag)  # same stamps
    np.testing.assert_allclose(off.truth.t_sample - on.truth.t_sample, 0.05, atol=1e-12)
    x0, x1 = off.truth.directions_body, on.truth.directions_body
    shifts = np.arange(-10, 11)
    match = [np.mean(np.sum(x1[10 + s:len(x1) - 10 + s] * x0[10:len(x0) - 10], axis=1))
             for s in shifts]
    # The lagged run at sample k + 5 shows what the unlagged one saw at k (5 samples = 50 ms).
    assert shifts[int(np.argmax(match))] == 5


def test_effects_do_not_change_the_motion_or_the_noise():
    a = _run(duration_s=20, effects={"temperature_offset": 0.1})
    b = _run(duration_s=20, effects={"temperature_offset": 0.1, "time_drift": 0.01})
    np.testing.assert_array_equal(a.truth.directions, b.truth.directions)
    assert a.truth.effects["temperature_offset"] == b.truth.effects["temperature_offset"]
    np.testing.assert_array_equal(a.track.accel, b.track.accel)


def test_effect_vector_can_be_given_exactly():
    res = _run(duration_s=5, effects={"time_drift": [0.1, 0.0, -0.2]})
    assert res.truth.effects["time_drift"]["d"] == [0.1, 0.0, -0.2]


# ---------------------------------------------------------------- outliers

def test_outlier_spans_match_the_disturbance(bursty):
    tr = bursty.truth
    spans = tr.outlier_spans
    assert spans.shape == (3, 2) and np.all(np.diff(spans.ravel()) > 0)
    assert np.all((spans[:, 1] - spans[:, 0] >= 2.0) & (spans[:, 1] - spans[:, 0] <= 5.0))
    disturbed = np.linalg.norm(tr.disturbance, axis=1) > 0
    assert not np.any(disturbed & ~tr.outlier_mask)
    # What a user sees: readings far from the clean model only inside the spans, and every span
    # has such readings.
    big = np.linalg.norm(bursty.track.mag - tr.mag_clean, axis=1) > 5.0
    assert not np.any(big & ~tr.outlier_mask)
    for s, e in spans:
        inside = (tr.t_mag >= s) & (tr.t_mag <= e)
        assert big[inside].sum() > 20
        assert np.linalg.norm(tr.disturbance[inside], axis=1).max() > 50.0


# ---------------------------------------------------------------- coverage and motion

def _bins_hit(x, n=200):
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    centres = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    return np.unique(np.argmax(x @ centres.T, axis=1)).size / n


@pytest.mark.parametrize("coverage", ["full", "hemisphere", "planar", "band"])
def test_coverage_patterns(coverage):
    res = _run(duration_s=120, seed=5, coverage=coverage)
    x = res.truth.directions_body
    z = x[:, 2]
    azimuth_span = np.ptp(np.unwrap(np.sort(np.arctan2(x[:, 1], x[:, 0]))))
    sin_dip = np.sin(np.radians(res.truth.dip_deg))
    if coverage == "full":
        assert _bins_hit(x) > 0.9
    elif coverage == "hemisphere":
        assert z.min() >= -1e-9 and z.max() > 0.95 and z.min() < 0.1
        assert 0.45 < _bins_hit(x) < 0.65
    elif coverage == "planar":
        np.testing.assert_allclose(z, -sin_dip, atol=1e-9)
        np.testing.assert_allclose(res.truth.up_body, np.tile([0, 0, 1.0], (len(z), 1)), atol=1e-9)
    else:
        lim = np.sin(np.radians(20))
        assert np.abs(z).max() <= lim + 1e-9 and np.abs(z).max() > 0.9 * lim
        assert z.min() < -0.8 * lim and _bins_hit(x) < 0.5
    assert azimuth_span > 1.9 * np.pi


def test_cumulative_rotation_matches_a_sequential_product():
    steps = Rotation.from_rotvec(0.3 * np.random.default_rng(0).standard_normal((37, 3)))
    seq = [steps[0]]
    for k in range(1, 37):
        seq.append(seq[-1] * steps[k])
    got = cumulative_rotation(steps)
    for k in (0, 1, 2, 5, 16, 36):
        assert (got[k] * seq[k].inv()).magnitude() < 1e-12


def test_gyro_rate_is_the_derivative_of_the_orientation():
    rng = np.random.default_rng(1)
    for coverage in ("full", "hemisphere"):
        mo = hand_motion(0.0, 5.0, rng, coverage=coverage, field_dir=np.array([0, 0.5, -0.866]),
                         dt=1e-3)
        dt = mo.t[1] - mo.t[0]
        fd = (mo.rotation[:-1].inv() * mo.rotation[1:]).as_rotvec() / dt
        mid = 0.5 * (mo.omega[:-1] + mo.omega[1:])
        assert np.abs(fd - mid).max() < 1e-2 * max(1.0, np.abs(mid).max())
        assert np.abs(mid).max() > 0.5


def test_still_pauses_are_still(base):
    tr = base.track
    early = tr.t[tr.gyro_rows] < 0.4  # every run starts with ≥ 0.5 s on the desk
    g = tr.gyro[early] - np.asarray(base.truth.imu["gyro_b"])
    assert np.abs(g).max() < 8 * np.radians(0.1)
    assert np.abs(np.linalg.norm(tr.accel[early], axis=1).mean() - 9.80665) < 0.3


def test_smooth_noise_has_the_requested_spread():
    x = smooth_noise(200_000, 1e-3, 0.5, 2.0, np.random.default_rng(0))
    assert x.shape == (200_000, 3)
    np.testing.assert_allclose(x.std(axis=0), 2.0, rtol=0.15)


# ---------------------------------------------------------------- paper protocol

def test_paper_protocol_statistics():
    m, K, b, inliers = paper_protocol(n=1000, sigma=1.0, eta=0.1, seed=4)
    assert m.shape == (1000, 3) and (~inliers).sum() == 100
    assert np.all(np.tril(K, -1) == 0) and np.all(np.diag(K) > 0)
    assert np.abs(K - 100 * np.eye(3)).max() < 60  # 0.1·σ_K·N(0,1) entries
    r = np.linalg.norm(np.linalg.solve(K, (m - b).T).T, axis=1)
    assert np.abs(r[inliers] - 1).max() < 0.06  # σ/σ_K = 0.01 per axis
    assert np.median(np.abs(r[~inliers] - 1)) > 0.1  # U(−100, 100) per element
    # Exactly on the ellipsoid without noise and outliers.
    m0, K0, b0, in0 = paper_protocol(n=500, sigma=0.0, eta=0.0, seed=4)
    assert in0.all()
    np.testing.assert_allclose(np.linalg.norm(np.linalg.solve(K0, (m0 - b0).T).T, axis=1), 1.0)
    # Deterministic per seed; b = σ_b (1 + N(0,1)) averages to σ_b over seeds.
    np.testing.assert_array_equal(paper_protocol(seed=4)[0], m)
    bs = np.array([paper_protocol(n=1, seed=s)[2] for s in range(400)])
    assert abs(bs.mean() - 20) < 2.5 and abs(bs.std() - 20) < 2.5


# ---------------------------------------------------------------- the bundled demo track

def test_bundled_demo_track_is_reproducible_and_does_not_tell_the_effect():
    import importlib.util
    from pathlib import Path

    from streamcal.inputs.track import Track
    root = Path(__file__).resolve().parent.parent
    path = root / "streamcal" / "data" / "demo_track.csv.gz"
    assert path.stat().st_size <= 1.5e6
    spec = importlib.util.spec_from_file_location("make_demo_track",
                                                  root / "tools" / "make_demo_track.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    made = tool.make()
    track = Track.read(path)
    assert set(track.columns) == set(made.track.columns)
    for name, col in made.track.columns.items():
        np.testing.assert_allclose(track.columns[name], col, atol=1e-9, equal_nan=True)
    meta = " ".join(f"{k} {v}" for k, v in track.metadata.items()).lower()
    assert "simulated" in meta and str(tool.SEED) in meta
    assert not any(name in meta for name in ("temperature_offset", "temperature", "effect"))
    assert np.ptp(made.truth.temp) > 12 and len(made.truth.outlier_spans) == 1
    assert abs(track.t[-1] - 180) < 0.1 and track.has("motor_current")
