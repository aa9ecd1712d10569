"""ROS bags as inputs: bags written by rosbags' own writers (ROS 1, ROS 2 sqlite3 and MCAP) from
the bundled demo track and from simulated data, read back by every command."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from streamcal.inputs import detect, read_recording
from streamcal.inputs.track import Track

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "streamcal" / "data" / "demo_track.csv.gz"
BASE_NS = 1_700_000_000 * 10**9          # an epoch stamp, as a robot's clock gives
KINDS = ("rosbag1", "sqlite3", "mcap")


def _typestore(kind: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if kind == "rosbag1" else Stores.ROS2_HUMBLE)


def _header(ts, kind, ns: int, frame: str):
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
    if kind == "rosbag1":
        return Header(seq=0, stamp=stamp, frame_id=frame)
    return Header(stamp=stamp, frame_id=frame)


def _messages(ts, kind, track: Track, *, battery: str | None, mag_frame: str, imu_frame: str):
    """``{(topic, msgtype): [(ns, msg), ...]}`` of the track's samples."""
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    MF, Imu = ts.types["sensor_msgs/msg/MagneticField"], ts.types["sensor_msgs/msg/Imu"]
    Temp, Batt = ts.types["sensor_msgs/msg/Temperature"], ts.types["sensor_msgs/msg/BatteryState"]
    c = track.columns
    ns_all = BASE_NS + np.round(c["t"] * 1e9).astype(np.int64)
    zeros9, no_orientation = np.zeros(9), np.r_[-1.0, np.zeros(8)]
    out = {("/imu/mag", MF.__msgtype__): [], ("/imu/data", Imu.__msgtype__): [],
           ("/imu/temperature", Temp.__msgtype__): []}
    if battery:
        out[("/battery", Batt.__msgtype__)] = []
    frames = (mag_frame,) if isinstance(mag_frame, str) else tuple(mag_frame)
    for i in range(len(ns_all)):
        ns = int(ns_all[i])
        if np.isfinite(c["mx"][i]):
            out[("/imu/mag", MF.__msgtype__)].append((ns, MF(
                header=_header(ts, kind, ns, frames[i % len(frames)]),
                magnetic_field=V3(x=c["mx"][i] * 1e-6, y=c["my"][i] * 1e-6, z=c["mz"][i] * 1e-6),
                magnetic_field_covariance=zeros9)))
        if "ax" in c and np.isfinite(c["ax"][i]):
            out[("/imu/data", Imu.__msgtype__)].append((ns, Imu(
                header=_header(ts, kind, ns, imu_frame),
                orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=no_orientation,
                angular_velocity=V3(x=c["gx"][i], y=c["gy"][i], z=c["gz"][i]),
                angular_velocity_covariance=zeros9,
                linear_acceleration=V3(x=c["ax"][i], y=c["ay"][i], z=c["az"][i]),
                linear_acceleration_covariance=zeros9)))
        if "temp" in c and np.isfinite(c["temp"][i]):
            out[("/imu/temperature", Temp.__msgtype__)].append((ns, Temp(
                header=_header(ts, kind, ns, imu_frame), temperature=c["temp"][i], variance=0.0)))
        if battery and np.isfinite(c[battery][i]):
            fields = dict(header=_header(ts, kind, ns, "battery"), voltage=12.0,
                          current=c[battery][i], charge=np.nan, capacity=np.nan,
                          design_capacity=np.nan, percentage=np.nan, power_supply_status=0,
                          power_supply_health=0, power_supply_technology=0, present=True,
                          cell_voltage=np.zeros(0), location="", serial_number="",
                          temperature=np.nan, cell_temperature=np.zeros(0))
            out[("/battery", Batt.__msgtype__)].append((ns, Batt(**fields)))
    return out


def write_bag(path: Path, kind: str, track: Track, *, battery: str | None = None,
              extra_mag_topic: bool = False, mag_frame: str | tuple = "imu_link",
              imu_frame: str = "imu_link") -> Path:
    """Write ``track`` as a bag with rosbags' writers: ``kind`` ``rosbag1`` (a ``.bag`` file),
    ``sqlite3`` or ``mcap`` (a ROS 2 bag directory); a tuple ``mag_frame`` is cycled over the
    MagneticField messages. Returns what to give streamcal."""
    ts = _typestore(kind)
    streams = _messages(ts, kind, track, battery=battery, mag_frame=mag_frame,
                        imu_frame=imu_frame)
    if extra_mag_topic:
        key = next(k for k in streams if k[0] == "/imu/mag")
        streams[("/mag_external", key[1])] = streams[key][::2]
    if kind == "rosbag1":
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    with writer:
        for (topic, msgtype), msgs in streams.items():
            if not msgs:
                continue
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for ns, msg in msgs:
                writer.write(conn, ns, serialize(msg, msgtype))
    return path


def _cli(*args, ok=True):
    proc = subprocess.run([sys.executable, "-m", "streamcal", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=240)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def _bag_name(kind: str) -> str:
    return "demo.bag" if kind == "rosbag1" else f"demo_{kind}"


@pytest.fixture(scope="module")
def demo():
    return Track.read(DEMO)


class _Bags(dict):
    """The demo track as a bag of each kind, written when first asked for (a test worker
    writes only the kinds its tests use)."""

    def __init__(self, root: Path, track: Track):
        super().__init__()
        self.root, self.track = root, track

    def __missing__(self, kind: str) -> Path:
        self[kind] = write_bag(self.root / _bag_name(kind), kind, self.track,
                               battery="motor_current")
        return self[kind]


@pytest.fixture(scope="module")
def demo_bags(tmp_path_factory, demo):
    return _Bags(tmp_path_factory.mktemp("bags"), demo)


@pytest.fixture(scope="module")
def demo_fit():
    return json.loads(_cli("fit", DEMO, "--json").stdout)


@pytest.mark.parametrize("kind", KINDS)
def test_bag_reads_as_the_track_it_was_written_from(demo_bags, demo, kind):
    bag = demo_bags[kind]
    assert detect(bag) == ("rosbag1" if kind == "rosbag1" else "rosbag2")
    track = read_recording(bag)
    t0 = demo.t[0]
    np.testing.assert_allclose(track.t_mag, demo.t_mag - t0, atol=2e-9)
    np.testing.assert_allclose(track.mag, demo.mag, rtol=1e-12, atol=1e-12)
    # each message is its own row: compare every column's samples and their times
    # (BatteryState.current is a float32 field)
    for name, source, rtol in (("ax", "ax", 1e-12), ("gz", "gz", 1e-12), ("temp", "temp", 1e-12),
                               ("battery_current_a", "motor_current", 1e-6)):
        got, want = track.columns[name], demo.columns[source]
        np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=rtol,
                                   atol=1e-7 if rtol > 1e-12 else 0)
        np.testing.assert_allclose(track.t[~np.isnan(got)], demo.t[~np.isnan(want)] - t0,
                                   atol=2e-9)
    md = track.metadata
    assert md["mag_topic"].startswith("/imu/mag (sensor_msgs/MagneticField, 17999 messages")
    assert md["imu_topic"].startswith("/imu/data (sensor_msgs/Imu,")
    assert md["temp_topic"].startswith("/imu/temperature") and md["battery_topic"].startswith("/battery")
    assert md["mag_frame_id"] == "imu_link" and md["imu_frame_id"] == "imu_link"
    assert md["mag_unit"] == "uT"


@pytest.mark.parametrize("kind", KINDS)
def test_fit_bag_equals_fit_track(demo_bags, demo_fit, kind):
    got = json.loads(_cli("fit", demo_bags[kind], "--json").stdout)
    np.testing.assert_allclose(got["K"], demo_fit["K"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["b"], demo_fit["b"], rtol=1e-9, atol=1e-9)
    assert got["n"] == demo_fit["n"] and got["n_outliers"] == demo_fit["n_outliers"]


def test_ros2_storage_file_alone_reads_its_bag_directory(demo_bags, demo):
    db3 = next(demo_bags["sqlite3"].glob("*.db3"))
    mcap = next(demo_bags["mcap"].glob("*.mcap"))
    assert detect(db3) == "rosbag2" and detect(mcap) == "rosbag2"
    for f in (db3, mcap):
        assert len(read_recording(f).t_mag) == len(demo.t_mag)


def test_commands_read_bags(demo_bags, tmp_path):
    bag = demo_bags["mcap"]
    out = tmp_path / "converted.csv"
    _cli("convert", bag, "-o", out)
    converted = Track.read(out)
    assert converted.metadata["mag_topic"].startswith("/imu/mag")
    assert converted.metadata["input_format"] == "rosbag2"
    _cli("diagnose", demo_bags["rosbag1"], "--json")
    _cli("fit", bag, "-o", tmp_path / "cal.json")
    _cli("apply", tmp_path / "cal.json", bag, "-o", tmp_path / "applied.csv")
    lines = (tmp_path / "applied.csv").read_text().splitlines()
    assert len([ln for ln in lines if not ln.startswith("#")]) == 17999 + 1
    _cli("report", bag, "-o", tmp_path / "report.html")
    assert (tmp_path / "report.html").stat().st_size > 10_000
    replay = _cli("replay", demo_bags["sqlite3"], "--json")
    assert json.loads(replay.stdout.strip().splitlines()[-1])
    summary = tmp_path / "summary.csv"
    _cli("batch", "fit", demo_bags["rosbag1"], bag, "--jobs", "1", "-o", summary)
    rows = summary.read_text().splitlines()
    assert len(rows) == 3 and all(",ok," in r for r in rows[1:])


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A simulated tumble (streamcal.sim) with a known hard iron, as a track and as bags with
    two MagneticField topics (the second at half rate) and mag/IMU in different frames."""
    from streamcal.sim import simulate

    sim = simulate(duration_s=40.0, seed=7)
    root = tmp_path_factory.mktemp("sim")
    track_path = root / "sim.csv"
    sim.track.write(track_path)
    bags = {kind: write_bag(root / ("sim.bag" if kind == "rosbag1" else f"sim_{kind}"), kind,
                            sim.track, extra_mag_topic=True, mag_frame="mag_link")
            for kind in ("rosbag1", "mcap")}
    return sim, track_path, bags


@pytest.mark.parametrize("kind", ("rosbag1", "mcap"))
def test_several_topics_need_topic(simulated, kind):
    _, track_path, bags = simulated
    proc = _cli("fit", bags[kind], ok=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "several sensor_msgs/MagneticField topics" in lines[0]
    assert "/imu/mag (sensor_msgs/MagneticField" in lines[0] and "/mag_external" in lines[0]
    assert "--topic" in lines[0]
    picked = json.loads(_cli("fit", bags[kind], "--topic", "/imu/mag", "--json").stdout)
    want = json.loads(_cli("fit", track_path, "--json").stdout)
    np.testing.assert_allclose(picked["K"], want["K"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(picked["b"], want["b"], rtol=1e-9, atol=1e-9)
    half = read_recording(bags[kind], topics=["/mag_external"])
    assert len(half.t_mag) == (len(Track.read(track_path).t_mag) + 1) // 2
    assert half.metadata["mag_frame_id"] == "mag_link"
    assert "differs" in half.metadata["mag_axes"]


def test_topic_errors_name_the_topics(simulated, demo_bags):
    _, _, bags = simulated
    proc = _cli("fit", bags["rosbag1"], "--topic", "/nope", ok=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "--topic /nope: no such topic" in proc.stderr and "/imu/data (sensor_msgs/Imu" in proc.stderr
    proc = _cli("fit", DEMO, "--topic", "/imu/mag", ok=False)
    assert proc.returncode == 2 and "--topic applies to ROS bags" in proc.stderr


def _one_line_exit_2(target):
    proc = _cli("fit", target, ok=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(target) in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    return lines[0]


@pytest.mark.parametrize("kind", KINDS)
def test_truncated_bag_is_one_line_exit_2(demo_bags, tmp_path, kind):
    import shutil

    bag = demo_bags[kind]
    if kind == "rosbag1":
        cut = tmp_path / "cut.bag"
        data = bag.read_bytes()
        cut.write_bytes(data[:len(data) // 2])
    else:
        cut = tmp_path / "cut"
        shutil.copytree(bag, cut)
        storage = next(f for f in cut.iterdir() if f.suffix in (".db3", ".mcap"))
        data = storage.read_bytes()
        storage.write_bytes(data[:len(data) // 2])
    line = _one_line_exit_2(cut)
    assert "truncated or damaged" in line


@pytest.mark.parametrize("kind", KINDS)
def test_empty_bag_is_one_line_exit_2(tmp_path, kind):
    empty = Track.from_arrays(np.zeros(0), mag=np.zeros((0, 3)))
    bag = write_bag(tmp_path / ("empty.bag" if kind == "rosbag1" else "empty"), kind, empty)
    line = _one_line_exit_2(bag)
    assert "no sensor_msgs/MagneticField topic" in line and "the bag is empty" in line


def test_directory_without_metadata_is_one_line(tmp_path):
    line = _one_line_exit_2(tmp_path)
    assert "a directory, not a recording" in line


@pytest.mark.parametrize("kind", ("rosbag1", "mcap"))
def test_real_track_as_a_bag_fits_the_same(real_tracks_dir, tmp_path, kind):
    track_path = real_tracks_dir / "sunsided_set2_fullsphere.csv.gz"
    bag = write_bag(tmp_path / ("real.bag" if kind == "rosbag1" else "real"), kind,
                    Track.read(track_path))
    got = json.loads(_cli("fit", bag, "--json").stdout)
    want = json.loads(_cli("fit", track_path, "--json").stdout)
    np.testing.assert_allclose(got["K"], want["K"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["b"], want["b"], rtol=1e-9, atol=1e-9)
    assert got["n"] == want["n"] == 8190


@pytest.mark.parametrize("kind", KINDS)
def test_numpy_decoding_equals_rosbags_per_message(demo_bags, monkeypatch, kind):
    from streamcal.inputs import rosbag_fields

    fast = read_recording(demo_bags[kind])
    monkeypatch.setattr(rosbag_fields, "_vectorized", lambda *args, **kw: None)
    slow = read_recording(demo_bags[kind])
    assert list(fast.columns) == list(slow.columns) and fast.metadata == slow.metadata
    for name in fast.columns:
        np.testing.assert_array_equal(fast.columns[name], slow.columns[name])


@pytest.mark.parametrize("kind", ("rosbag1", "mcap"))
def test_messages_of_different_lengths_are_read_one_by_one(simulated, tmp_path, monkeypatch,
                                                           kind):
    """Frame ids of different lengths: no fixed layout, rosbags deserializes each message."""
    from streamcal.inputs import rosbag_fields

    sim, track_path, _ = simulated
    bag = write_bag(tmp_path / ("frames.bag" if kind == "rosbag1" else "frames"), kind,
                    sim.track, mag_frame=("mag", "magnetometer_link"))
    calls = []
    one_by_one = rosbag_fields._one_by_one
    monkeypatch.setattr(rosbag_fields, "_one_by_one",
                        lambda raws, msgtype, *a: calls.append(msgtype) or one_by_one(raws, msgtype, *a))
    track = read_recording(bag)
    assert calls == ["sensor_msgs/msg/MagneticField"]
    np.testing.assert_allclose(track.mag, Track.read(track_path).mag, rtol=1e-12)
    assert track.metadata["mag_frame_id"] == "mag,magnetometer_link"


MELODIC_BATTERY_STATE = """\
std_msgs/Header header
float32 voltage
float32 current
float32 charge
float32 capacity
float32 design_capacity
float32 percentage
uint8 power_supply_status
uint8 power_supply_health
uint8 power_supply_technology
bool present
float32[] cell_voltage
string location
string serial_number
"""


def test_ros1_bag_is_read_with_its_own_message_definitions(tmp_path):
    """A ROS 1 melodic BatteryState has no temperature field: read with noetic's layout its
    current would be the charge. The reader uses the definitions the bag carries."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    noetic = get_typestore(Stores.ROS1_NOETIC)
    melodic = get_typestore(Stores.EMPTY)
    melodic.register({k: v for k, v in noetic.fielddefs.items()
                      if k != "sensor_msgs/msg/BatteryState"})
    melodic.register(get_types_from_msg(MELODIC_BATTERY_STATE, "sensor_msgs/msg/BatteryState"))
    MF, V3 = melodic.types["sensor_msgs/msg/MagneticField"], melodic.types["geometry_msgs/msg/Vector3"]
    Batt = melodic.types["sensor_msgs/msg/BatteryState"]
    bag = tmp_path / "melodic.bag"
    with Writer(bag) as writer:
        mag = writer.add_connection("/imu/mag", MF.__msgtype__, typestore=melodic)
        batt = writer.add_connection("/battery", Batt.__msgtype__, typestore=melodic)
        for k in range(5):
            ns = BASE_NS + k * 10**8
            writer.write(mag, ns, melodic.serialize_ros1(MF(
                header=_header(melodic, "rosbag1", ns, "imu"),
                magnetic_field=V3(x=2e-5, y=0.0, z=4e-5),
                magnetic_field_covariance=np.zeros(9)), MF.__msgtype__))
            writer.write(batt, ns, melodic.serialize_ros1(Batt(
                header=_header(melodic, "rosbag1", ns, "battery"), voltage=12.5,
                current=1.5 + k, charge=99.0, capacity=np.nan, design_capacity=np.nan,
                percentage=0.5, power_supply_status=0, power_supply_health=0,
                power_supply_technology=0, present=True, cell_voltage=np.zeros(0),
                location="", serial_number=""), Batt.__msgtype__))
    link = tmp_path / "melodic_recording"          # a ROS 1 bag without the .bag suffix
    link.write_bytes(bag.read_bytes())
    for path in (bag, link):
        track = read_recording(path)
        current = track.columns["battery_current_a"]
        np.testing.assert_allclose(current[np.isfinite(current)], 1.5 + np.arange(5))
        np.testing.assert_allclose(track.mag[0], [20.0, 0.0, 40.0])


def test_magnetometer_without_finite_values_is_one_line(tmp_path):
    from rosbags.rosbag1 import Writer

    ts = _typestore("rosbag1")
    MF, V3 = ts.types["sensor_msgs/msg/MagneticField"], ts.types["geometry_msgs/msg/Vector3"]
    bag = tmp_path / "nan.bag"
    with Writer(bag) as writer:
        conn = writer.add_connection("/imu/mag", MF.__msgtype__, typestore=ts)
        for k in range(3):
            ns = BASE_NS + k * 10**7
            writer.write(conn, ns, ts.serialize_ros1(MF(
                header=_header(ts, "rosbag1", ns, "imu"),
                magnetic_field=V3(x=np.nan, y=np.nan, z=np.nan),
                magnetic_field_covariance=np.zeros(9)), MF.__msgtype__))
    line = _one_line_exit_2(bag)
    assert "/imu/mag has no finite magnetic field values" in line
