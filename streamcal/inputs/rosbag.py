"""ROS bags → Track, read with :mod:`rosbags` (no ROS installation needed).

A ROS 1 ``.bag`` file, or a ROS 2 bag: its directory (``metadata.yaml`` beside ``.db3`` sqlite3
or ``.mcap`` files) or one of its storage files. Messages read:

=============================== ======================================= =====================
``sensor_msgs/MagneticField``   magnetic_field x, y, z (T)              ``mx,my,mz`` µT (×1e6)
``sensor_msgs/Imu``             linear_acceleration (m/s²),             ``ax..az``, ``gx..gz``
                                angular_velocity (rad/s)
``sensor_msgs/Temperature``     temperature (°C)                        ``temp``
``sensor_msgs/BatteryState``    current (A; NaN = not measured)         ``battery_current_a``
=============================== ======================================= =====================

An ``Imu`` whose ``linear_acceleration_covariance[0]`` (or ``angular_velocity_covariance[0]``)
is −1 declares that field absent (REP 145); such fields are left out. Time is each message's
``header.stamp`` (the bag's receive time when a topic's stamps are all zero), shifted so the
earliest message is t = 0. One topic of each type is used: the only one in the bag, or the one
named with ``topics`` (``--topic NAME``, repeatable) when there are several. Topics, types,
frame ids and message counts go into the track's metadata.
"""
from __future__ import annotations

import tempfile
from contextlib import ExitStack
from pathlib import Path
from typing import Iterable

import numpy as np

from ..errors import InputError
from .rosbag_fields import decode
from .streams import Stream, merge

ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"
UT_PER_TESLA = 1e6

#: kind → ROS message type (rosbags' normalised name); the magnetometer comes first
MESSAGE_TYPES = {"mag": "sensor_msgs/msg/MagneticField", "imu": "sensor_msgs/msg/Imu",
                 "temp": "sensor_msgs/msg/Temperature", "battery": "sensor_msgs/msg/BatteryState"}


def looks_like_rosbag1(head: bytes) -> bool:
    return head.startswith(ROSBAG1_MAGIC)


def looks_like_rosbag2_file(head: bytes) -> bool:
    """A ROS 2 storage file (sqlite3 ``.db3`` or ``.mcap``)."""
    return head.startswith((SQLITE_MAGIC, MCAP_MAGIC))


def is_rosbag2_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _ros_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Imu`` → ``sensor_msgs/Imu`` (how ROS users write it)."""
    return msgtype.replace("/msg/", "/")


def _open(path: Path, fmt: str, stack: ExitStack):
    """``(reader, description)``: an open :class:`rosbags.highlevel.AnyReader`, which
    deserializes with the message definitions the bag carries (a ROS 1 melodic
    ``BatteryState`` is not noetic's), else with the stock ROS 2 types."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if fmt == "rosbag1":
        target, what = path, "ROS 1 bag"
        if path.suffix != ".bag":
            # AnyReader tells ROS 1 from ROS 2 by the .bag suffix; the content said ROS 1
            link = Path(stack.enter_context(tempfile.TemporaryDirectory())) / f"{path.name}.bag"
            link.symlink_to(path.resolve())
            target = link
    else:
        target = path
        if path.is_file() and is_rosbag2_dir(path.parent):
            target = path.parent                  # the whole bag: every split file
        elif path.is_file() and path.suffix not in (".db3", ".mcap"):
            storage = "sqlite3" if read_magic(path).startswith(SQLITE_MAGIC) else "mcap"
            raise InputError(f"{path}: a ROS 2 {storage} storage file without its bag directory "
                             f"(metadata.yaml); give the bag directory, or name the file "
                             f"{'.db3' if storage == 'sqlite3' else '.mcap'}")
        what = f"ROS 2 bag ({_storage(target)})"
    reader = AnyReader([target], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    reader.open()
    stack.callback(reader.close)
    return reader, what


def read_magic(path: Path) -> bytes:
    with open(path, "rb") as handle:
        return handle.read(16)


def _storage(target: Path) -> str:
    files = [target] if target.is_file() else sorted(target.iterdir())
    kinds = {"sqlite3" if f.suffix == ".db3" else "mcap" for f in files
             if f.suffix in (".db3", ".mcap")}
    return "+".join(sorted(kinds)) or "unknown storage"


def _choose(connections, path: Path, wanted: Iterable[str]) -> dict[str, str]:
    """``{kind: topic}`` for the kinds present; raises when a type has several topics and
    ``wanted`` names none of them, or when ``wanted`` names a topic not in the bag."""
    wanted = list(dict.fromkeys(wanted or ()))
    types: dict[str, str] = {}
    counts: dict[str, int] = {}
    for c in connections:
        types.setdefault(c.topic, c.msgtype)
        counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount or 0)

    def listing(names):
        return ", ".join(f"{t} ({_ros_name(types[t])}, {counts[t]} messages)" for t in names)

    for topic in wanted:
        if topic not in types:
            raise InputError(f"{path}: --topic {topic}: no such topic in the bag; its topics: "
                             f"{listing(sorted(types)) or 'none'}")
        if types[topic] not in MESSAGE_TYPES.values():
            raise InputError(f"{path}: --topic {topic} is a {_ros_name(types[topic])} topic; "
                             "streamcal reads " + ", ".join(map(_ros_name, MESSAGE_TYPES.values())))
    chosen = {}
    for kind, msgtype in MESSAGE_TYPES.items():
        candidates = sorted(t for t, ty in types.items() if ty == msgtype)
        picked = [t for t in wanted if t in candidates]
        if len(picked) > 1:
            raise InputError(f"{path}: --topic names several {_ros_name(msgtype)} topics "
                             f"({', '.join(picked)}); give one")
        if picked:
            chosen[kind] = picked[0]
        elif len(candidates) == 1:
            chosen[kind] = candidates[0]
        elif candidates:
            raise InputError(f"{path}: several {_ros_name(msgtype)} topics: {listing(candidates)}; "
                             "pick one with --topic NAME")
    if "mag" not in chosen:
        raise InputError(f"{path}: no {_ros_name(MESSAGE_TYPES['mag'])} topic in the bag; its "
                         f"topics: {listing(sorted(types)) or 'none (the bag is empty)'}")
    return chosen


def _stamps(fields: dict, received: list[int]) -> tuple[np.ndarray, str]:
    """(n,) int64 ns of the header stamps, or of the receive times when all stamps are zero."""
    stamps = fields["stamp_ns"]
    if len(stamps) and not stamps.any():
        return np.asarray(received, dtype=np.int64), "bag receive time (header stamps all zero)"
    return stamps, "header.stamp"


def _columns(kind: str, fields: dict, meta: dict, topic: str) -> dict[str, np.ndarray]:
    if kind == "mag":
        return dict(zip(("mx", "my", "mz"), (fields["magnetic_field"] * UT_PER_TESLA).T))
    if kind == "imu":
        cols = {}
        for field, names in (("linear_acceleration", ("ax", "ay", "az")),
                             ("angular_velocity", ("gx", "gy", "gz"))):
            if np.all(fields[f"{field}_covariance0"] == -1):
                meta[f"{topic}.{field}"] = "declared absent (covariance[0] = -1); left out"
                continue
            cols.update(zip(names, fields[field].T))
        return cols
    if kind == "temp":
        return {"temp": fields["temperature"][:, 0]}
    return {"battery_current_a": fields["current"][:, 0]}


def read_rosbag(path, fmt: str, *, topics: Iterable[str] | None = None):
    """Read a ROS bag (``fmt`` ``rosbag1`` or ``rosbag2`` from :func:`~.detect.detect`) into a
    Track (see the module docstring). ``topics``: names picking one topic per message type.

    Raises :class:`InputError` naming the bag for a damaged or truncated bag, a bag without a
    ``MagneticField`` topic, or a type with several topics none of which ``topics`` names.
    """
    path = Path(path)
    stack = ExitStack()
    try:
        reader, what = _open(path, fmt, stack)
        deserialize = reader.deserialize
        chosen = _choose(reader.connections, path, topics or ())
        meta = {"sensor": "ros magnetometer", "source": f"{what} {path.name}",
                "input_format": fmt, "mag_unit": "uT",
                "units": "mx,my,mz uT (from tesla x1e6); ax,ay,az m/s^2; gx,gy,gz rad/s; "
                         "temp degC; battery_current_a A"}
        streams, t_ns, frames = [], [], {}
        for kind, topic in chosen.items():
            conns = [c for c in reader.connections if c.topic == topic]
            raws, received = [], []
            for _, stamp, raw in reader.messages(connections=conns):
                raws.append(bytes(raw))
                received.append(stamp)
            if not raws:
                if kind == "mag":
                    raise InputError(f"{path}: topic {topic} ({_ros_name(MESSAGE_TYPES[kind])}) "
                                     "has no messages")
                continue
            fields = decode(raws, MESSAGE_TYPES[kind], deserialize, ros2=fmt == "rosbag2")
            ns, stamp_source = _stamps(fields, received)
            cols = _columns(kind, fields, meta, topic)
            keep = np.ones(len(ns), dtype=bool)
            for values in cols.values():
                keep &= np.isfinite(values)
            frames[kind] = fields["frame_ids"]
            meta[f"{kind}_topic"] = (f"{topic} ({_ros_name(MESSAGE_TYPES[kind])}, {len(raws)} "
                                     f"messages, time from {stamp_source})")
            meta[f"{kind}_frame_id"] = ",".join(f or "''" for f in frames[kind])
            if not keep.all():
                meta[f"{kind}_dropped"] = f"{int((~keep).sum())} messages with NaN values"
            if cols and keep.any():
                streams.append((kind, ns[keep], {k: v[keep] for k, v in cols.items()}))
                t_ns.append(int(ns[keep].min()))
    except InputError:
        raise
    except Exception as exc:   # rosbags, sqlite and the deserializers raise assorted types
        raise InputError(f"{path}: cannot read the ROS bag ({type(exc).__name__}: {exc}); the "
                         "bag is truncated or damaged") from None
    finally:
        try:
            stack.close()
        except Exception:   # closing a damaged bag must not hide why it failed
            pass
    if not streams or streams[0][0] != "mag":
        raise InputError(f"{path}: topic {chosen['mag']} has no finite magnetic field values")
    t0 = min(t_ns)
    mag_frames, imu_frames = frames.get("mag", []), frames.get("imu")
    meta["mag_axes"] = f"frame {meta['mag_frame_id']} of the MagneticField messages"
    if imu_frames is not None and imu_frames != mag_frames:
        meta["mag_axes"] += (f"; the Imu frame ({','.join(imu_frames)}) differs: streamcal takes "
                             "them as the same axes (no tf is applied)")
    meta["time_origin"] = f"stamp {t0 / 1e9:.9f} s is t = 0"
    meta["messages"] = ", ".join(f"{chosen[kind]} {len(ns)}" for kind, ns, _ in streams)
    return merge([Stream(chosen[kind], (ns - t0) * 1e-9, cols) for kind, ns, cols in streams],
                 meta, t0=0.0)
