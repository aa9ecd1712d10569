"""PX4 ULog files (``.ulg``) → Track, read with :mod:`pyulog`.

Magnetometer ``N`` (``--compass N``: the topics' multi-instance ``N``; default the first by
CAL_MAGn_PRIO among the ``sensor_mag`` instances, else 0), from whichever of these topics has the
most samples of that instance; ties go to the uncalibrated one:

===================== ============================= =========================================
``sensor_mag``        x, y, z (G), temperature (°C)  the driver's reading, not calibrated
``vehicle_magnetometer`` magnetometer_ga[0..2] (G)   calibrated by PX4 (CAL_MAGn_*, rotated)
``sensor_combined``   magnetometer_ga[0..2] (G)      older logs; calibrated by PX4's driver
===================== ============================= =========================================

``sensor_mag`` of older PX4 (up to 1.11, the layout with ``x_raw``/``scaling``) was published by
the driver already corrected ``(r − o) · scale`` per axis with CAL_MAGn_xOFF/xSCALE; the reader
undoes that (``r = c / scale + o``) and says so in ``mag_driver_calibration_undone``.

Gauss → µT is ×100. PX4 corrects ``c = R S (r − o)`` (``o`` = CAL_MAGn_XOFF.. in G, ``S`` the
symmetric matrix of CAL_MAGn_XSCALE../XODIAG.., ``R`` the board/external rotation). For a
calibrated topic the reader undoes ``S`` and ``o`` (``r = S⁻¹ c + o``) when ``R`` is the identity
(CAL_MAGn_ROT ≤ 0 and SENS_BOARD_ROT = 0) and says so in the metadata; otherwise it keeps the
calibrated field and says why. Power compensation (CAL_MAGn_XCOMP) is not undone; when it is
non-zero the metadata says so.

Also: ``sensor_combined`` accelerometer_m_s2 / gyro_rad → ``ax..az``, ``gx..gz``;
``actuator_outputs.output[i]`` → ``act_out{i}`` (outputs that never change are left out);
``actuator_controls_0.control[3]`` (or, from 1.14, the length of ``vehicle_thrust_setpoint.xyz``)
→ ``throttle`` (0..1, the signal of PX4's throttle-based compass compensation); ``battery_status`` current_a / voltage_v → ``battery_current_a``,
``battery_voltage_v`` (a second battery, instance 1: ``battery2_current_a``, …).
Time is the ULog timestamp (µs), shifted so the log starts at 0 s.

A log cut inside a message (a crash, a power cut) is read to its last complete message; a damaged
stretch is cut out up to the next valid message (:mod:`.ulog_framing`), with or without sync
messages. Both are said in ``read_warnings``, with the bytes lost.
"""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from ..errors import InputError
from .autopilot_cal import UT_PER_GAUSS, px4_matrix, px4_offsets
from .track import Track
from .streams import Stream, drop_nonfinite, merge
from .attitude_streams import ulog_attitude
from .ulog_framing import framing, kept_bytes

MAGIC = b"ULog\x01\x12\x35"
MAG_TOPICS = (("sensor_mag", ("x", "y", "z"), False),
              ("vehicle_magnetometer", tuple(f"magnetometer_ga[{i}]" for i in range(3)), True),
              ("sensor_combined", tuple(f"magnetometer_ga[{i}]" for i in range(3)), True))


def looks_like_ulog(head: bytes) -> bool:
    return head[:7] == MAGIC


class _PaddedReads(io.BytesIO):
    """The log's bytes for pyulog, as if the file went on past its end for relative seeks.

    pyulog, on a damaged header near the end, reads the message size it announces and seeks back
    by that size + 2 to advance one byte; a read cut short by the end of the file turns that
    into a step backwards and an endless loop. Here a relative seek after a short read counts
    from where the full read would have ended, so the step is one byte forward as intended."""

    _virtual: int | None = None

    def read(self, n=-1):
        start = self.tell()
        data = super().read(n)
        self._virtual = start + n if n is not None and 0 <= len(data) < n else None
        return data

    def seek(self, offset, whence=0):
        if whence == 1 and self._virtual is not None:
            offset, whence = max(self._virtual + offset, 0), 0
        self._virtual = None
        return super().seek(offset, whence)


def _load(path: Path):
    from pyulog import ULog  # imported only when a ULog is read

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    found = framing(data)
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter):   # pyulog prints its warnings
            ulog = ULog(_PaddedReads(kept_bytes(data, found)))
    except Exception as exc:  # pyulog raises assorted exception types on damaged bytes
        raise InputError(f"{path}: cannot read the ULog ({type(exc).__name__}: {exc})") from None
    return ulog, len(data) - found.end, found.skipped


def _topic(ulog, name: str, instance: int | None = None):
    """The data of topic ``name``: its multi-instance ``instance``, or the lowest one."""
    found = [d for d in ulog.data_list if d.name == name
             and (instance is None or d.multi_id == instance)]
    if not found:
        return None
    return min(found, key=lambda d: d.multi_id)


def _mag_topics(ulog, instance: int | None = None) -> list:
    """[(samples, uncalibrated, name, fields, calibrated, data)] of the magnetometer topics with
    samples (of multi-instance ``instance`` when given)."""
    out = []
    for name, fields, calibrated in MAG_TOPICS:
        for d in ulog.data_list:
            if d.name != name or (instance is not None and d.multi_id != instance):
                continue
            if all(f in d.data for f in fields) and len(d.data["timestamp"]):
                out.append((len(d.data["timestamp"]), not calibrated, name, fields, calibrated, d))
    return out


def compass_instances(ulog) -> list[int]:
    """The magnetometer instances (topic multi-instances) with samples."""
    return sorted({c[5].multi_id for c in _mag_topics(ulog)})


def default_compass(ulog) -> int:
    """The magnetometer PX4 uses first: the ``sensor_mag`` instance whose CAL_MAGn_PRIO is the
    highest (the lowest instance on ties); in logs without CAL_MAGn_PRIO (PX4 up to 1.11) the
    one whose device id is CAL_MAG_PRIME; else 0."""
    params = ulog.initial_parameters
    prime = None if any(k.startswith("CAL_MAG") and k.endswith("_PRIO") for k in params) \
        else params.get("CAL_MAG_PRIME")
    best = None
    for d in sorted((d for d in ulog.data_list if d.name == "sensor_mag"),
                    key=lambda d: d.multi_id):
        if "device_id" not in d.data or not len(d.data["device_id"]):
            continue
        device = int(d.data["device_id"][0])
        i = _cal_index(params, device)
        prio = params.get(f"CAL_MAG{i}_PRIO", 0) if i is not None else 0
        if prime:
            prio = 1 if device == int(prime) else 0
        if best is None or prio > best[0]:
            best = (prio, d.multi_id)
    present = compass_instances(ulog)
    return best[1] if best is not None and best[1] in present else (present or [0])[0]


def _cal_index(params: dict, device_id) -> int | None:
    if device_id is None:
        prime = params.get("CAL_MAG_PRIME")
        device_id = prime if prime else params.get("CAL_MAG0_ID")
    for i in range(4):
        if device_id and params.get(f"CAL_MAG{i}_ID") == device_id:
            return i
    return None


def _cal_prefix(params: dict, device_id, meta: dict) -> str | None:
    """``CAL_MAGn_`` of the calibration PX4 applies to ``device_id`` (recorded in ``meta``)."""
    i = _cal_index(params, device_id)
    if i is None:
        return None
    meta["mag_cal_params"] = f"CAL_MAG{i}_"
    return meta["mag_cal_params"]


def _undo_px4(mag_g: np.ndarray, params: dict, device_id, meta: dict) -> np.ndarray:
    """``r = S⁻¹ c + o`` for the CAL_MAGn of ``device_id`` when the rotation is the identity."""
    p = _cal_prefix(params, device_id, meta)
    if p is None:
        meta["mag_calibration_undone"] = ("could not: no CAL_MAGn_ID matches the magnetometer's "
                                          "device id; mx,my,mz are PX4's calibrated field")
        return mag_g
    rot = int(params.get(p + "ROT", -1))
    board = int(params.get("SENS_BOARD_ROT", 0))
    if rot > 0 or board != 0:
        meta["mag_calibration_undone"] = (f"could not: {p}ROT={rot}, SENS_BOARD_ROT={board} "
                                          "rotate the field; mx,my,mz are PX4's calibrated field")
        return mag_g
    off = px4_offsets(params, p)
    raw = np.linalg.solve(px4_matrix(params, p), mag_g.T).T + off
    trims = [params.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in "XYZ"]
    meta["mag_calibration_undone"] = (
        f"{p}XOFF.. added back ({','.join(f'{v:g}' for v in off)} G) and the inverse of the "
        f"{p}SCALE/ODIAG matrix applied (PX4 corrects c = S (r - o))"
        + (f"; board trim SENS_BOARD_X/Y/Z_OFF = {','.join(f'{v:g}' for v in trims)} deg not undone"
           if any(trims) else ""))
    if any(params.get(p + a + "COMP", 0.0) for a in "XYZ"):
        meta["mag_power_compensation"] = f"{p}XCOMP.. non-zero: PX4's power compensation not undone"
    return raw


#: Fields of ``sensor_mag`` as PX4's drivers published it while they applied the calibration
#: themselves (``PX4Magnetometer`` up to 1.11): x, y, z are then ``(r − o) · scale`` per axis.
DRIVER_CALIBRATED_FIELDS = ("x_raw", "scaling", "range_ga")


def _driver_calibrated(d) -> bool:
    """Whether ``sensor_mag`` data ``d`` carries the driver-calibrated layout."""
    return any(f in d.data for f in DRIVER_CALIBRATED_FIELDS)


def _undo_driver(mag_g: np.ndarray, params: dict, device_id, meta: dict) -> np.ndarray:
    """``r = c / scale + o`` per axis: the driver's CAL_MAGn_xSCALE and xOFF undone (it applied
    them in its own frame, the frame of ``c``, before any board rotation)."""
    p = _cal_prefix(params, device_id, meta)
    if p is None:
        meta["mag_driver_calibration_undone"] = (
            "could not: no CAL_MAGn_ID matches the magnetometer's device id; mx,my,mz carry "
            "the driver's offsets and scales")
        return mag_g
    scale = np.array([params.get(f"{p}{a}SCALE", 1.0) or 1.0 for a in "XYZ"], dtype=float)
    off = px4_offsets(params, p)
    meta["mag_driver_calibration_undone"] = (
        f"sensor_mag of this layout ({', '.join(DRIVER_CALIBRATED_FIELDS[:2])}) is the driver's "
        f"(r - {p}XOFF..) * {p}XSCALE..: divided by the scales "
        f"({','.join(f'{v:g}' for v in scale)}) and the offsets "
        f"({','.join(f'{v:g}' for v in off)} G) added back")
    return mag_g / scale + off


def _mag(ulog, path: Path, meta: dict, instance: int) -> Stream:
    candidates = _mag_topics(ulog, instance)
    if not candidates:
        present = compass_instances(ulog)
        if present:
            raise InputError(f"{path}: no magnetometer {instance} in this log (magnetometers "
                             f"with data: {', '.join(map(str, present))})")
        raise InputError(f"{path}: no magnetometer topic (looked for sensor_mag.x/y/z, "
                         "vehicle_magnetometer.magnetometer_ga, sensor_combined.magnetometer_ga; "
                         f"topics found: {', '.join(sorted({d.name for d in ulog.data_list}))})")
    _, _, name, fields, calibrated, d = max(candidates, key=lambda c: c[:2])
    t = d.data["timestamp"] * 1e-6
    mag_g = np.column_stack([d.data[f].astype(np.float64) for f in fields])
    if name == "sensor_combined":
        # each row carries the latest mag sample; keep one row per new sample
        new = np.r_[True, np.any(np.diff(mag_g, axis=0) != 0, axis=1)]
        if "magnetometer_timestamp_relative" in d.data:
            t = t + d.data["magnetometer_timestamp_relative"] * 1e-6
        t, mag_g = t[new], mag_g[new]
    meta["mag_topic"] = f"{name} (instance {d.multi_id}, {len(t)} samples, gauss x100 = uT)"
    meta["mag_calibrated_by_px4"] = "yes" if calibrated else "no (driver reading)"
    device_id = int(d.data["device_id"][0]) if "device_id" in d.data else None
    if device_id:
        meta["compass_device_id"] = str(device_id)
    params = ulog.initial_parameters
    if not calibrated and _driver_calibrated(d):
        mag_g = _undo_driver(mag_g, params, device_id, meta)
    if calibrated:
        # the strength PX4's corrected field has: the scale of its calibration (--cal log)
        meta["autopilot_field_uT"] = f"{np.median(np.linalg.norm(mag_g, axis=1)) * UT_PER_GAUSS:.4g}"
        mag_g = _undo_px4(mag_g, params, device_id, meta)
    elif (p := _cal_prefix(params, device_id, meta)) is not None:
        corrected = (mag_g - px4_offsets(params, p)) @ px4_matrix(params, p).T
        meta["autopilot_field_uT"] = (
            f"{np.median(np.linalg.norm(corrected, axis=1)) * UT_PER_GAUSS:.4g}")
    cols = dict(zip(("mx", "my", "mz"), (mag_g * UT_PER_GAUSS).T))
    if "temperature" in d.data and np.any(d.data["temperature"] != 0) \
            and np.all(np.isfinite(d.data["temperature"])):
        cols["temp"] = d.data["temperature"].astype(np.float64)[:len(t)]
        meta["temp_source"] = f"{name}.temperature (the magnetometer's)"
    return Stream(name, t, cols)


def _imu(ulog) -> Stream | None:
    d = _topic(ulog, "sensor_combined")
    fields = [f"accelerometer_m_s2[{i}]" for i in range(3)] + [f"gyro_rad[{i}]" for i in range(3)]
    if d is None or not all(f in d.data for f in fields):
        return None
    cols = dict(zip(("ax", "ay", "az", "gx", "gy", "gz"),
                    (d.data[f].astype(np.float64) for f in fields)))
    return Stream("sensor_combined", d.data["timestamp"] * 1e-6, cols)


def _actuators(ulog, meta: dict) -> Stream | None:
    d = _topic(ulog, "actuator_outputs")
    if d is None:
        return None
    cols, constant = {}, []
    for i in range(32):
        key = f"output[{i}]"
        if key not in d.data:
            break
        values = d.data[key].astype(np.float64)
        if not np.all(np.isfinite(values)) or np.all(values == values[0]):
            constant.append(f"act_out{i}")
            continue
        cols[f"act_out{i}"] = values
    meta["actuator_outputs"] = ",".join(cols) or "none"
    if constant:
        meta["actuator_outputs_dropped"] = f"{len(constant)} outputs constant or non-finite"
    return Stream("actuator_outputs", d.data["timestamp"] * 1e-6, cols) if cols else None


def _throttle(ulog, meta: dict) -> Stream | None:
    """The throttle PX4's CAL_MAG_COMP_TYP = 1 compensation scales with, when logged and not
    constant: ``actuator_controls_0.control[3]`` (0..1), or, from PX4 1.14 (which dropped the
    actuator_controls topics), the length of ``vehicle_thrust_setpoint.xyz`` (instance 0)."""
    d = _topic(ulog, "actuator_controls_0")
    if d is not None and "control[3]" in d.data:
        values, name = d.data["control[3]"].astype(np.float64), "actuator_controls_0"
        source = "actuator_controls_0.control[3] (0..1)"
    else:
        d = _topic(ulog, "vehicle_thrust_setpoint", 0)
        fields = [f"xyz[{i}]" for i in range(3)]
        if d is None or not all(f in d.data for f in fields):
            return None
        values = np.linalg.norm(np.column_stack([d.data[f].astype(np.float64) for f in fields]),
                                axis=1)
        name, source = "vehicle_thrust_setpoint", "|vehicle_thrust_setpoint.xyz| (0..1)"
    if not np.all(np.isfinite(values)) or np.all(values == values[0]):
        return None
    meta["throttle_source"] = source
    return Stream(name, d.data["timestamp"] * 1e-6, {"throttle": values})


def _battery(ulog, meta: dict) -> list[Stream]:
    """``battery_status`` of every battery: instance 0 as ``battery_current_a``,
    ``battery_voltage_v``, instance k ≥ 1 as ``battery{k+1}_current_a``, ``…_voltage_v``."""
    out, said = [], []
    for d in sorted((d for d in ulog.data_list if d.name == "battery_status"),
                    key=lambda d: d.multi_id):
        prefix = "battery" if d.multi_id == 0 else f"battery{d.multi_id + 1}"
        cols = {}
        for key, quantity in (("current_a", "current_a"), ("voltage_v", "voltage_v")):
            if key in d.data:
                values = d.data[key].astype(np.float64)
                # PX4 logs -1 for "no current measurement"
                if np.all(np.isfinite(values)) and not np.all(values == values[0]):
                    cols[f"{prefix}_{quantity}"] = values
        said += list(cols)
        if cols:
            name = "battery_status" if d.multi_id == 0 else f"battery_status {d.multi_id}"
            out.append(Stream(name, d.data["timestamp"] * 1e-6, cols))
    if any(d.name == "battery_status" for d in ulog.data_list):
        meta["battery_channels"] = ",".join(said) or "none (constant or not measured)"
    return out


def read_ulog(path, *, skip_bad_rows: bool = False, compass: int | None = None) -> Track:
    """Read magnetometer ``compass`` (default: the one PX4 uses first) of a PX4 ``.ulg`` log
    into a Track (see the module docstring).

    A cut or damaged log is read as far as it goes (``read_warnings`` says what was lost;
    ``skip_bad_rows`` changes nothing for a log). Raises :class:`InputError` naming the file
    when it has no magnetometer topic (or not that instance).
    """
    path = Path(path)
    ulog, cut, skipped = _load(path)
    with _damaged(path):
        return _track(ulog, path, cut, default_compass(ulog) if compass is None else compass,
                      skipped)


def read_ulog_compasses(path, *, skip_bad_rows: bool = False) -> list[Track]:
    """One Track per magnetometer instance of the log (the log is parsed once)."""
    path = Path(path)
    ulog, cut, skipped = _load(path)
    with _damaged(path):
        tracks = [_track(ulog, path, cut, i, skipped) for i in compass_instances(ulog) or [0]]
        for track in tracks:
            track.metadata["compass_default"] = str(default_compass(ulog))
    return tracks


@contextlib.contextmanager
def _damaged(path: Path):
    """InputError naming the file when pyulog parsed damaged definitions into fields of the
    wrong type (a flipped byte in a format message makes ``device_id`` a string, …)."""
    try:
        yield
    except (ValueError, TypeError, KeyError, IndexError, OverflowError) as exc:
        raise InputError(f"{path}: the ULog's message definitions are damaged "
                         f"({type(exc).__name__}: {exc})") from None


def _skipped_text(skipped: list) -> str:
    """What the damaged stretches cost (:func:`.ulog_framing.framing`'s ``skipped``)."""
    if not skipped:   # the framing was intact, pyulog found damaged contents
        return "Skipped damaged data (pyulog found messages it could not parse)"
    runs = ", ".join(f"{n} at offset {at}" for at, n in skipped[:5])
    more = f" and {len(skipped) - 5} more runs" if len(skipped) > 5 else ""
    return (f"Skipped damaged data: {sum(n for _, n in skipped)} bytes in {len(skipped)} "
            f"run{'s' if len(skipped) > 1 else ''} ({runs}{more}) held no valid message; read on "
            "from the next valid one")


def _track(ulog, path: Path, cut: int, instance: int, skipped=()) -> Track:
    info = ulog.msg_info_dict
    meta = {"sensor": f"px4 magnetometer (instance {instance})",
            "source": f"PX4 ULog {path.name}", "compass_instance": str(instance),
            "compasses_in_log": ",".join(map(str, compass_instances(ulog))),
            "input_format": "px4-ulog", "mag_unit": "uT",
            "units": "mx,my,mz uT (from gauss x100); ax,ay,az m/s^2; gx,gy,gz rad/s; temp degC; "
                     "act_out* as logged by actuator_outputs; throttle 0..1; battery_current_a A; "
                     "battery_voltage_v V"}
    for key in ("ver_hw", "ver_sw", "sys_name"):
        if key in info:
            meta[f"px4_{key}"] = str(info[key]).strip() or "?"
    streams = [_mag(ulog, path, meta, instance)]
    meta["mag_axes"] = ("body frame (PX4 rotated it)" if meta["mag_calibrated_by_px4"] == "yes"
                        else "the sensor's own frame (sensor_mag): PX4 turns it into the body "
                             "frame after its calibration by CAL_MAGn_ROT, SENS_BOARD_ROT for "
                             "an internal compass")
    for stream in (_imu(ulog), _actuators(ulog, meta), _throttle(ulog, meta),
                   *_battery(ulog, meta)):
        if stream is not None:
            streams.append(stream)
    streams += ulog_attitude(ulog, meta)
    for name, value in ulog.initial_parameters.items():
        if name.startswith(("CAL_MAG0_", meta.get("mag_cal_params", "CAL_MAG0_"))) \
                or name in ("CAL_MAG_PRIME", "CAL_MAG_COMP_TYP", "SENS_BOARD_ROT"):
            meta[f"param.{name}"] = f"{value:g}"
    if cut:
        meta["read_warnings"] = (f"truncated: {cut} trailing bytes ignored (the log ends inside "
                                 "a message; read to the last complete one)")
    if ulog.file_corruption or skipped:
        meta["read_warnings"] = (meta.get("read_warnings", "") + "; " if "read_warnings" in meta
                                 else "") + _skipped_text(skipped)
    streams = drop_nonfinite(streams, meta)
    if not len(streams[0].t):
        raise InputError(f"{path}: no intact magnetometer sample ({meta['read_warnings']})")
    t0 = min(float(s.t.min()) for s in streams if len(s.t))
    meta["time_origin"] = f"ULog timestamp {t0:.6f} s is t = 0"
    meta["log_t0_s"] = f"{t0:.6f}"
    meta["messages"] = ", ".join(f"{s.name} {len(s.t)}" for s in streams)
    return merge(streams, meta, t0=t0)
