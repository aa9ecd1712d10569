"""The attitude and GPS position the log readers bring (streamcal.inputs.attitude_streams), on
self-made message tables and on the real logs."""
import datetime
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from streamcal.constants import ATTITUDE_COLUMNS
from streamcal.inputs.attitude_streams import (continuous_quaternions, dataflash_attitude,
                                               euler_to_quaternions, gps_week_date, ulog_attitude)


class _Msgs:
    """The DataFlash reader's message table, from plain columns."""

    def __init__(self, cols):
        self.cols = {k: {c: np.asarray(v, float) for c, v in d.items()} for k, d in cols.items()}

    def has(self, name, *columns):
        return name in self.cols and all(c in self.cols[name] for c in columns)

    def count(self, name):
        return len(next(iter(self.cols[name].values()))) if name in self.cols else 0

    def array(self, name, column):
        return self.cols[name][column]


def _yaw_pitch_roll(q_wxyz):
    return Rotation.from_quat(q_wxyz[:, [1, 2, 3, 0]]).as_euler("ZYX", degrees=True)


def test_euler_becomes_the_body_to_ned_quaternion():
    q = euler_to_quaternions([10.0, -170.0], [5.0, 30.0], [350.0, 90.0])
    ypr = _yaw_pitch_roll(q)
    assert ypr[0] == pytest.approx([-10.0, 5.0, 10.0])
    assert ypr[1] == pytest.approx([90.0, 30.0, -170.0])
    # yaw 90°, pitch 30° up: body forward (x) points east and up (NED: z negative)
    forward = Rotation.from_quat(q[1, [1, 2, 3, 0]]).apply([1.0, 0.0, 0.0])
    assert forward == pytest.approx([0.0, np.cos(np.radians(30)), -0.5], abs=1e-9)


def test_signs_stay_on_one_hemisphere():
    q = np.array([[1.0, 0, 0, 0], [-0.999, -0.01, 0, 0], [0.998, 0.02, 0, 0]])
    out = continuous_quaternions(q)
    assert np.all(np.einsum("ij,ij->i", out[1:], out[:-1]) > 0)
    assert np.allclose(np.abs(out), np.abs(q))


def test_gps_week_counts_from_1980():
    assert gps_week_date(1823, 147_999_000) == datetime.date(2014, 12, 15)
    assert gps_week_date(0, 0) is None


def test_dataflash_new_layout_keeps_instance_0_and_3d_fixes():
    msgs = _Msgs({
        "ATT": {"TimeUS": [0, 1e5, 2e5], "Roll": [0, 1, 2], "Pitch": [0, 0, 0],
                "Yaw": [359.0, 0.5, 1.5]},
        "GPS": {"TimeUS": [0, 1, 2, 3], "I": [0, 1, 0, 0], "Status": [3, 3, 1, 4],
                "Lat": [47.0, 10.0, 0.0, 47.2], "Lng": [8.0, 10.0, 0.0, 8.2],
                "Alt": [400.0, 0, 0, 410.0], "GWk": [2300] * 4, "GMS": [86_400_000] * 4}})
    meta = {}
    streams = dataflash_attitude(msgs, lambda n: msgs.array(n, "TimeUS") * 1e-6, meta)
    assert len(streams) == 1 and set(streams[0].columns) == set(ATTITUDE_COLUMNS)
    q = np.column_stack([streams[0].columns[c] for c in ATTITUDE_COLUMNS])
    assert np.all(np.einsum("ij,ij->i", q[1:], q[:-1]) > 0.99)   # 359° → 0.5°: no sign jump
    assert float(meta["gps_lat_deg"]) == pytest.approx(47.1)
    assert float(meta["gps_lon_deg"]) == pytest.approx(8.1)
    assert meta["gps_date"] == "2024-02-05"     # week 2300 starts 2024-02-04, + 1 day
    assert "2 fixes" in meta["gps_source"]


def test_dataflash_without_fix_has_no_position():
    msgs = _Msgs({"AHR2": {"TimeUS": [0, 1], "Roll": [0, 0], "Pitch": [0, 0], "Yaw": [0, 0],
                           "Lat": [0, 0], "Lng": [0, 0]},
                  "GPS": {"TimeUS": [0], "Status": [1], "Lat": [47.0], "Lng": [8.0]}})
    meta = {}
    streams = dataflash_attitude(msgs, lambda n: msgs.array(n, "TimeUS") * 1e-6, meta)
    assert meta["attitude_source"].startswith("AHR2") and len(streams) == 1
    assert "gps_lat_deg" not in meta


def _topic(name, **data):
    return SimpleNamespace(name=name, multi_id=0, data={k: np.asarray(v) for k, v in data.items()})


def test_ulog_attitude_and_sensor_gps():
    q = Rotation.from_euler("ZYX", [[30, 0, 0], [40, 5, 0]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    ulog = SimpleNamespace(data_list=[
        _topic("vehicle_attitude", timestamp=[0, 1000], **{f"q[{i}]": q[:, i] for i in range(4)}),
        _topic("sensor_gps", timestamp=[0, 1], fix_type=[2, 3], latitude_deg=[1.0, 47.5],
               longitude_deg=[1.0, 8.5], altitude_msl_m=[0.0, 500.0],
               time_utc_usec=[0, 1_700_000_000_000_000])])
    meta = {}
    streams = ulog_attitude(ulog, meta)
    got = np.column_stack([streams[0].columns[c] for c in ATTITUDE_COLUMNS])
    assert got == pytest.approx(q)
    assert meta["gps_lat_deg"] == "47.5000000" and meta["gps_date"] == "2023-11-14"


def test_real_logs_attitude_matches_the_logged_angles(flight_dir):
    from streamcal.inputs import read_recording
    from streamcal.inputs.dataflash import _parse

    path = flight_dir / "ardupilot_erle_Erle-Brain3.BIN"
    track = read_recording(path)
    msgs = _parse(path)
    rows = ~np.isnan(track.columns["att_qw"])
    q = np.column_stack([track.columns[c][rows] for c in ATTITUDE_COLUMNS])
    ypr = _yaw_pitch_roll(q)
    yaw = msgs.array("ATT", "Yaw")
    assert len(q) == len(yaw)
    assert np.allclose((ypr[:, 0] - yaw + 180) % 360 - 180, 0, atol=1e-6)
    assert np.allclose(ypr[:, 2], msgs.array("ATT", "Roll"), atol=1e-6)
    assert "gps_lat_deg" not in track.metadata      # AHR2/GPS carry no fix on this log
    assert "att_qw" not in track.aux_names
