"""Calibration is a value: read-only K and b, equality on the saved content, one strict loader,
JSON round trip, one radius formula."""
import os

import numpy as np
import pytest

from streamcal.calibration import Calibration, field_radius
from streamcal.errors import CalibrationFileError

K = np.array([[50.0, 1.0, -2.0], [0.0, 47.0, 0.5], [0.0, 0.0, 52.0]])
B = np.array([10.0, -5.0, 3.0])


def _cal(**kw):
    base = dict(K=K, b=B, model=("hard_iron", "soft_iron"), rms=0.4, n=1000, n_outliers=7,
                coverage=0.8, field=49.6, kernel="cauchy", created="2026-01-01T00:00:00Z",
                extra={"tau": 1.1, "noise_sigma": 0.3})
    base.update(kw)
    return Calibration(**base)


def test_K_and_b_are_read_only_and_the_callers_arrays_are_not():
    k, b = K.copy(), B.copy()
    cal = _cal(K=k, b=b)
    with pytest.raises(ValueError):
        cal.K[0, 0] = 1.0
    with pytest.raises(ValueError):
        cal.b[0] = 1.0
    k[0, 0] = 1.0                      # the caller's array stays writeable and separate
    assert cal.K[0, 0] == 50.0


def test_equality_is_on_saved_content_not_per_sample_results():
    a = _cal(inliers=np.ones(5, bool), weights=np.ones(5))
    b = _cal(inliers=np.zeros(5, bool))
    assert a == b and hash(a) == hash(b)
    assert a != _cal(rms=0.41)
    assert a != _cal(b=B + [0, 0, 1e-9])
    assert a.inliers is not None and a.inliers.all()   # still there (SPEC §5 cal.inliers)
    assert "inliers" not in a.to_dict()


def test_json_round_trip_is_equal(tmp_path):
    cal = _cal(rms=float("nan"))
    again = Calibration.from_json(cal.to_json())
    assert again == cal and again.to_json() == cal.to_json()
    path = tmp_path / "cal.json"
    cal.save(path)
    loaded = Calibration.load(path)
    assert loaded == cal
    assert not loaded.K.flags.writeable
    assert np.array_equal(loaded.K, K) and np.array_equal(loaded.b, B)


def test_load_refuses_a_symlink_and_a_huge_file(tmp_path):
    target = tmp_path / "real.json"
    _cal().save(target)
    link = tmp_path / "link.json"
    os.symlink(target, link)
    with pytest.raises(CalibrationFileError, match="symbolic link"):
        Calibration.load(link)
    big = tmp_path / "big.json"
    big.write_bytes(b" " * ((1 << 20) + 10))
    with pytest.raises(CalibrationFileError, match="too large"):
        Calibration.load(big)
    with pytest.raises(CalibrationFileError, match="cannot read"):
        Calibration.load(tmp_path / "missing.json")
    log = tmp_path / "flight.bin"
    log.write_bytes(bytes([0xA3, 0x95, 0x80, 0x80]) + bytes(range(256)))   # a DataFlash head
    with pytest.raises(CalibrationFileError, match="not a calibration file: .* byte 0 .* flight log"):
        Calibration.load(log)


def test_radius_is_the_cube_root_of_det_K():
    cal = _cal()
    assert cal.radius == pytest.approx((50.0 * 47.0 * 52.0) ** (1 / 3), rel=1e-12)
    assert field_radius(K) == cal.radius


def test_saved_file_names_the_residual_its_rms_is_on(tmp_path):
    import json
    plain = _cal()
    tied = _cal(model=("hard_iron", "soft_iron", "time_lag"),
                extra={"gyro_tied": {"pairs": 10}, "tau": 1.1})
    for cal, expected in ((plain, "sensor"), (tied, "gyro_tied")):
        path = tmp_path / f"{expected}.json"
        cal.save(path)
        data = json.loads(path.read_text())
        assert data["residual"] == expected
        again = Calibration.load(path)
        assert again == cal and "residual" not in again.extra


def test_a_residual_outside_the_three_families_is_refused(tmp_path):
    import json
    data = _cal().to_dict()
    data["residual"] = "whatever"
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="residual"):
        Calibration.load(path)
