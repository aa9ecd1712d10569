"""ArduPilot DataFlash logs (``.bin``) → Track, decoded in bulk by :mod:`.dataflash_bulk` (a
header walk + a numpy structured dtype per message type; values identical to
:mod:`pymavlink.DFReader`'s, which stays callable as :func:`read_dataflash_pymavlink`, about
45× slower by ``tools/bench_flight.py``).

What is taken (message layouts differ between firmware versions, so fields are found by name):

====== ================================ ==================================================
MAG    MagX/Y/Z mG, OfsX/Y/Z, MOfsX/Y/Z  ``mx,my,mz`` µT (1 mG = 0.1 µT), offsets undone
IMU    AccX/Y/Z m/s², GyrX/Y/Z rad/s     ``ax..az``, ``gx..gz``; ``Temp`` → ``temp`` if not 0
RCOU   C1…C14 or Ch1…Ch12, µs            ``rcou_c1``… (PWM outputs; unused ones left out)
CURR   Volt, Curr, Throttle or ThrOut    ``battery_voltage_v``, ``battery_current_a``, ``throttle``
BAT    Volt, Curr (newer firmware)       as CURR; battery k ≥ 1 (BAT.Inst = k, or CUR2/BAT2) as
                                         ``battery{k+1}_voltage_v``, ``battery{k+1}_current_a``
                                         (:mod:`.dataflash_battery`)
CTUN   ThO (0..1) or ThrOut (0..1000)    ``throttle`` when CURR has none (3.4 and later);
       (plane, rover: percent)           a rover's THR.ThrOut (percent) where no CTUN has it
BARO   Temp °C                           ``temp`` when IMU has no temperature (said so)
PARM   Name, Value                       the compass's COMPASS_* in the metadata (``param.NAME``)
VER    FWS (4.1 and later)               ``firmware``, the version text; else the MSG that names it
====== ================================ ==================================================

Time is ``TimeUS`` (µs) or ``TimeMS`` (ms), shifted to start at 0 s; each message is its own row.

Compasses: instance ``N`` (from 0) is ``MAG``/``MAG2``/``MAG3`` in older layouts, the rows of
``MAG`` whose field ``I`` is ``N`` in newer ones; its parameters are COMPASS_OFS_*, DIA_*, ODI_*,
MOT_* for instance 0 and COMPASS_OFS2_*, DIA2_*, … (``3`` for instance 2) for the others
(:func:`~.autopilot_cal.ardupilot_param`), or, when COMPASS_PRIOn_ID are logged (4.0 on, where
the logged instance is the priority), the set whose COMPASS_DEV_IDn is that compass's. The default compass is COMPASS_PRIMARY when it is
logged and that compass has rows, else instance 0. IMU, BAT, BARO: instance 0.

The throttle ArduPilot's COMPASS_MOTCT = 1 compensation scales with (``motors->get_throttle()``)
is CURR.Throttle/ThrOut in Copter 3.2–3.3, CTUN.ThO from 3.4 on (a plane's CURR.Throttle is the
pilot's input in percent: its CTUN.ThrOut is taken); when neither is logged it is
approximated by the motor outputs: the mean over the motor channels of RCOU normalised by the
PWM range (:mod:`.dataflash_throttle`: the SERVOn_FUNCTION 33–40 motors, a plane's throttle
channel, else channels 1–4), said in ``throttle_source``.

A log cut inside a message (a crash, a power cut) is read to its last complete message; a
damaged stretch is skipped to the next valid message header; both are counted in
``read_warnings``.

ArduPilot logs the *corrected* field (``Compass::get_field``, int16 mG): with COMPASS_OFS = ``o``
(added), the motor offsets ``MOfs`` (``mot · c``, logged as applied) and the soft-iron matrix
``S`` of COMPASS_DIA/ODI, ``MAG = S (raw + o) + MOfs`` from Copter 3.6 / Plane 3.9 / Rover 3.3 on,
``MAG = S (raw + o + MOfs)`` before (:func:`~.autopilot_cal.ardupilot_correction_order`, from the
version in the log's VER message or MSG text; the current order when none is logged). The reader returns
``raw = S⁻¹ (MAG − MOfs) − o`` or ``raw = S⁻¹ MAG − MOfs − o`` with ``o`` and ``MOfs`` taken per
sample from the MAG message itself, and says in the metadata what it undid and in which order
(``ardupilot_correction_order``, ``ardupilot_correction_order_from``).
"""
from __future__ import annotations

import contextlib
import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .track import Track
from .autopilot_cal import (FIRMWARE_VERSION, MG_PER_UT, ardupilot_param, ardupilot_param_index,
                            compass_params)
from .streams import Stream, drop_nonfinite, merge
from .dataflash_bulk import MAGIC, decode, walk
from .attitude_streams import DATAFLASH_MESSAGES, dataflash_attitude
from .dataflash_throttle import ctun_throttle, rcou_throttle
from .dataflash_battery import battery_streams, rows_of
from .dataflash_mag import mag_meta, mag_values

MESSAGES = ("MAG", "MAG2", "MAG3", "IMU", "RCOU", "CURR", "CUR2", "BAT", "BAT2", "BARO", "CTUN",
            "THR", "PARM", "MSG", "VER")
MESSAGES += DATAFLASH_MESSAGES  # attitude and GPS: .attitude_streams
MAG_NAMES = ("MAG", "MAG2", "MAG3")
#: PWM outputs are 0 (off/unused) or roughly 800–2200 µs; anything outside this is not PWM.
PWM_RANGE_US = (0.0, 3000.0)


@dataclass
class _Messages:
    """Columns of each message type: ``cols[name][column]`` (float64, or object for strings)
    in log order, ``fields[name]`` the FMT column names, ``types[name]`` column → format char."""

    fields: dict = field(default_factory=dict)
    types: dict = field(default_factory=dict)
    cols: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    texts: list = field(default_factory=list)
    path: Path | None = None

    def array(self, name: str, column: str) -> np.ndarray:
        try:
            return np.asarray(self.cols[name][column], dtype=np.float64)
        except (TypeError, ValueError):
            kind = self.types.get(name, {}).get(column, "?")
            raise InputError(f"{self.path}: {name}.{column} is not a number (format character "
                             f"{kind!r}): unknown layout") from None

    def has(self, name: str, *columns: str) -> bool:
        return name in self.cols and all(c in self.fields[name] for c in columns)

    def count(self, name: str) -> int:
        return len(next(iter(self.cols[name].values()), ())) if name in self.cols else 0


def looks_like_dataflash(head: bytes) -> bool:
    """True if ``head`` (the first bytes of a file) starts a DataFlash log: a FMT message."""
    return head[:2] == MAGIC and head[2:3] == b"\x80"


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None


def _parse(path: Path) -> _Messages:
    """The wanted messages, decoded in bulk (:mod:`.dataflash_bulk`)."""
    data = _read_bytes(path)
    chain = walk(data)
    out = _Messages(path=path)
    for name in MESSAGES:
        ftype = chain.name_to_type.get(name)
        if ftype is None or ftype not in chain.offsets:
            continue
        fmt = chain.formats[ftype]
        try:
            cols = decode(data, fmt, chain.offsets[ftype])
        except ValueError as exc:
            raise InputError(f"{path}: cannot read the DataFlash log ({exc}): unknown layout") \
                from None
        if name == "PARM" and {"Name", "Value"} <= set(cols):
            add_params(out.params, cols, path)
        elif name == "MSG" and "Message" in cols:
            out.texts += [str(m) for m in cols["Message"].tolist()]
        elif name not in ("PARM", "MSG"):
            out.fields[name] = list(fmt.columns)
            out.cols[name] = cols
            out.types[name] = dict(zip(fmt.columns, fmt.format))
    out.texts += walk_notes(chain)
    return out


def walk_notes(chain) -> list[str]:
    """What the walk of a log lost (a cut, skipped runs, trailing bytes), one text each."""
    notes = []
    if chain.cut > 0:
        notes.append(f"truncated: {chain.cut} trailing bytes ignored (the log ends inside a "
                     "message; read to the last complete one)")
    if chain.skipped:
        runs = ", ".join(f"{n} at offset {at}" for at, n in chain.skipped[:5])
        more = f" and {len(chain.skipped) - 5} more runs" if len(chain.skipped) > 5 else ""
        notes.append(f"Skipped {sum(n for _, n in chain.skipped)} bad bytes ({runs}{more}): "
                     "resynchronised on the next message header")
    if chain.trailing:
        notes.append(f"Skipped {chain.trailing} trailing bytes after the last message "
                     "(no message header)")
    return notes


def add_params(params: dict, cols: dict, path: Path) -> None:
    """PARM rows (``Name``, ``Value`` columns) into ``params``, the last value of a name kept."""
    for key, value in zip(cols["Name"].tolist(), cols["Value"].tolist()):
        try:
            params[str(key)] = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{path}: PARM {key!s:.40}: value {value!r:.40} is not a number: "
                             "unknown layout") from None


def _parse_pymavlink(path: Path) -> _Messages:
    """The same through :class:`pymavlink.DFReader.DFReader_binary` (an object per message,
    ~10× slower): the reference the equivalence test compares :func:`_parse` against."""
    from pymavlink import DFReader  # heavy (lxml, ~0.5 s): imported only when asked for

    cut = walk(_read_bytes(path)).cut
    out = _Messages(path=path)
    rows: dict = {}
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
            while True:
                msg = reader.recv_match(type=list(MESSAGES))
                if msg is None:
                    break
                name = msg.get_type()
                if name == "PARM":
                    out.params[str(msg.Name)] = float(msg.Value)
                    continue
                if name == "MSG":
                    out.texts.append(str(msg.Message))
                    continue
                if name not in rows:
                    out.fields[name] = list(msg.get_fieldnames())
                    rows[name] = []
                rows[name].append(tuple(getattr(msg, f) for f in out.fields[name]))
            formats = {fmt.name: fmt for fmt in reader.formats.values()}
    except Exception as exc:  # pymavlink raises assorted exception types on damaged bytes
        raise InputError(f"{path}: cannot read the DataFlash log ({type(exc).__name__}: {exc})") \
            from None
    for name, table in rows.items():
        out.cols[name] = {}
        for k, column in enumerate(out.fields[name]):
            values = [row[k] for row in table]
            try:
                out.cols[name][column] = np.array(values, dtype=np.float64)
            except (TypeError, ValueError):
                out.cols[name][column] = np.array(values, dtype=object)
        out.types[name] = dict(zip(formats[name].columns, formats[name].format))
    if cut > 0:
        out.texts.append(f"truncated: {cut} trailing bytes ignored (the log ends inside a "
                         "message; read to the last complete one)")
    if "Skipped" in chatter.getvalue():
        out.texts.append(chatter.getvalue().strip().splitlines()[0])
    return out


def _time(msgs: _Messages, name: str, path: Path) -> np.ndarray:
    if msgs.has(name, "TimeUS"):
        return msgs.array(name, "TimeUS") * 1e-6
    if msgs.has(name, "TimeMS"):
        return msgs.array(name, "TimeMS") * 1e-3
    raise InputError(f"{path}: message {name} has neither TimeUS nor TimeMS (fields: "
                     f"{', '.join(msgs.fields[name])}): unknown layout")


def compass_instances(msgs: _Messages) -> list[int]:
    """The compass instances (from 0) that have MAG rows in the log."""
    if msgs.has("MAG", "I"):
        return sorted(int(i) for i in np.unique(msgs.array("MAG", "I")))
    return [i for i, name in enumerate(MAG_NAMES) if msgs.count(name)]


def default_compass(msgs: _Messages) -> int:
    """The compass ArduPilot uses first: COMPASS_PRIMARY when logged and present, else 0."""
    present = compass_instances(msgs)
    primary = int(msgs.params.get("COMPASS_PRIMARY", 0) or 0)
    return primary if primary in present else 0


def _mag_rows(msgs: _Messages, path: Path, instance: int) -> tuple[_Messages, str]:
    """(messages with the rows of compass ``instance``, the message name holding them)."""
    present = compass_instances(msgs)
    if not present:
        raise InputError(f"{path}: no MAG messages: this log has no magnetometer data "
                         f"(messages found: {', '.join(sorted(msgs.cols)) or 'none'})")
    if instance not in present:
        raise InputError(f"{path}: no compass {instance} in this log (compasses with data: "
                         f"{', '.join(map(str, present))})")
    name = "MAG" if msgs.has("MAG", "I") else MAG_NAMES[instance]
    if not msgs.has(name, "MagX", "MagY", "MagZ"):
        raise InputError(f"{path}: {name} message without MagX/MagY/MagZ (fields: "
                         f"{', '.join(msgs.fields[name])}): unknown layout")
    return rows_of(msgs, name, instance), name


def _mag(msgs: _Messages, path: Path, meta: dict, instance: int) -> Stream:
    params_of = ardupilot_param_index(msgs.params, instance)
    meta["compass_params_index"] = str(params_of)
    msgs, name = _mag_rows(msgs, path, instance)
    logged = np.column_stack([msgs.array(name, c) for c in ("MagX", "MagY", "MagZ")])
    meta["autopilot_field_uT"] = f"{np.median(np.linalg.norm(logged, axis=1)) / MG_PER_UT:.4g}"
    # only what mag_meta words need: mag_values below reads the offsets itself
    mofs_nonzero = msgs.has(name, "MOfsX", "MOfsY", "MOfsZ") and \
        any(np.any(msgs.array(name, c)) for c in ("MOfsX", "MOfsY", "MOfsZ"))
    ofs_sets = np.unique(np.column_stack([msgs.array(name, c) for c in ("OfsX", "OfsY", "OfsZ")]),
                         axis=0) if msgs.has(name, "OfsX", "OfsY", "OfsZ") else None
    mag_meta(msgs, name, params_of, meta, bool(mofs_nonzero), ofs_sets)
    return Stream(name, _time(msgs, name, path), mag_values(msgs, name, params_of, logged,
                                                          meta["ardupilot_correction_order"]))


def slow_streams(msgs: _Messages, path: Path, meta: dict, baro: bool) -> list[Stream]:
    """The low-rate streams beside the compass and the IMU, in the track's order: the
    barometer's temperature (when ``baro``: the IMU logs none), the motor outputs, the
    batteries, the attitude and the throttle (when no CURR carries it)."""
    out = []
    if baro:
        out.append(_baro_temp(msgs, path, meta))
    out.append(_rcou(msgs, path, meta))
    out += battery_streams(msgs, lambda rows, name: _time(rows, name, path), meta)
    out += dataflash_attitude(msgs, lambda name: _time(msgs, name, path), meta)
    if "throttle_source" not in meta:
        def time_of(name):
            return _time(msgs, name, path)

        out.append(ctun_throttle(msgs, time_of, meta) or rcou_throttle(msgs, time_of, meta))
    return [s for s in out if s is not None]


def compass_meta(msgs: _Messages, params_of: int, meta: dict) -> None:
    """The compass's device id and parameters in force, and what a damaged log lost, into
    ``meta``."""
    device = msgs.params.get(ardupilot_param("DEV_ID", params_of))
    if device:
        meta["compass_device_id"] = f"{int(device)}"
    for name, value in compass_params(msgs.params, params_of).items():
        meta[f"param.{name}"] = f"{value:g}"
    notes = [m for m in msgs.texts if m.startswith(("truncated", "Skipped"))]
    if notes:
        meta["read_warnings"] = "; ".join(notes)


def _imu(msgs: _Messages, path: Path, meta: dict) -> Stream | None:
    names = ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ")
    if not msgs.has("IMU", *names) or not msgs.count("IMU"):
        return None
    msgs = rows_of(msgs, "IMU")
    cols = dict(zip(("ax", "ay", "az", "gx", "gy", "gz"), (msgs.array("IMU", c) for c in names)))
    if msgs.has("IMU", "Temp"):
        temp = msgs.array("IMU", "Temp")
        if np.any(temp != 0):
            cols["temp"] = temp
            meta["temp_source"] = "IMU.Temp (the IMU's die temperature)"
    return Stream("IMU", _time(msgs, "IMU", path), cols)


def _baro_temp(msgs: _Messages, path: Path, meta: dict) -> Stream | None:
    if not msgs.has("BARO", "Temp") or not msgs.count("BARO"):
        return None
    msgs = rows_of(msgs, "BARO")
    meta["temp_source"] = ("BARO.Temp (the barometer's temperature, not the magnetometer's; "
                           "IMU logs no temperature)")
    return Stream("BARO", _time(msgs, "BARO", path), {"temp": msgs.array("BARO", "Temp")})


def _rcou(msgs: _Messages, path: Path, meta: dict) -> Stream | None:
    if not msgs.count("RCOU"):
        return None
    cols, dropped, unused = {}, [], []
    for name in msgs.fields["RCOU"]:
        match = re.fullmatch(r"C(?:h)?(\d+)", name)
        if not match:
            continue
        values = msgs.array("RCOU", name)
        label = f"rcou_c{int(match.group(1))}"
        if values.min() < PWM_RANGE_US[0] or values.max() > PWM_RANGE_US[1]:
            dropped.append(f"{label} (values {values.min():g}..{values.max():g} outside "
                           f"{PWM_RANGE_US[0]:g}..{PWM_RANGE_US[1]:g} us: not a PWM output)")
            continue
        if np.all(values == values[0]):
            unused.append(label)  # never driven, or a constant that carries nothing
            continue
        cols[label] = values
    meta["rcou_channels"] = ",".join(cols) or "none"
    if unused:
        meta["rcou_constant_dropped"] = ",".join(unused)
    if dropped:
        meta["rcou_dropped"] = "; ".join(dropped)
    return Stream("RCOU", _time(msgs, "RCOU", path), cols) if cols else None


def read_dataflash(path, *, skip_bad_rows: bool = False, compass: int | None = None) -> Track:
    """Read compass ``compass`` (instance from 0; default: the one ArduPilot uses first) of an
    ArduPilot DataFlash ``.bin`` log into a Track (see the module docstring).

    A log cut inside a message is read to its last complete message and a damaged stretch is
    skipped; both are said in ``read_warnings`` (``skip_bad_rows`` changes nothing for a log).
    Raises :class:`InputError` naming the file and the message when the log has no MAG messages
    (or not that compass) or a layout without the needed fields.
    """
    path = Path(path)
    msgs = _parse(path)
    return _track(msgs, path, default_compass(msgs) if compass is None else compass)


def read_dataflash_compasses(path, *, skip_bad_rows: bool = False) -> list[Track]:
    """One Track per compass of the log, in instance order (the log is parsed once)."""
    path = Path(path)
    msgs = _parse(path)
    present = compass_instances(msgs)
    if not present:
        _mag_rows(msgs, path, 0)   # raises: no MAG messages
    tracks = [_track(msgs, path, i) for i in present]
    for track in tracks:
        track.metadata["compass_default"] = str(default_compass(msgs))
    return tracks


def read_dataflash_pymavlink(path, *, skip_bad_rows: bool = False,
                             compass: int | None = None) -> Track:
    """:func:`read_dataflash` with the messages decoded by pymavlink's DFReader instead of the
    bulk decoder (much slower): the reference of the equivalence test and the read benchmark."""
    path = Path(path)
    msgs = _parse_pymavlink(path)
    return _track(msgs, path, default_compass(msgs) if compass is None else compass)


def head_meta(msgs: _Messages, path: Path, instance: int, present) -> dict:
    """The metadata every track of a log starts with: what it is, the compass ``instance``
    among the ``present`` ones, units, and the firmware's version text when logged."""
    meta = {"sensor": f"ardupilot compass (instance {instance})",
            "source": f"ArduPilot DataFlash log {path.name}",
            "input_format": "ardupilot-dataflash", "mag_unit": "uT",
            "compass_instance": str(instance),
            "compasses_in_log": ",".join(map(str, present)),
            "mag_axes": "body frame (ArduPilot rotates by COMPASS_ORIENT/AHRS_ORIENTATION "
                        "before logging)",
            "units": "mx,my,mz uT (from mG /10); ax,ay,az m/s^2; gx,gy,gz rad/s; temp degC; "
                     "rcou_c* us; battery_current_a A; battery_voltage_v V; throttle 0..1"}
    firmware = firmware_text(msgs)
    if firmware:
        meta["firmware"] = firmware
    return meta


def firmware_text(msgs: _Messages) -> str | None:
    """The firmware's version text: VER's firmware string (FWS, logged from 4.1 on, e.g.
    "ArduCopter V4.3.7 (f1a2b3c4)") when it names a vehicle and version, else the first MSG
    text that does, else the first MSG text with a version; None when the log has none."""
    versions = [str(v) for v in msgs.cols["VER"]["FWS"].tolist()] if msgs.has("VER", "FWS") \
        else []
    return next((m for m in versions + msgs.texts if FIRMWARE_VERSION.search(m)), None) or \
        next((m for m in msgs.texts if re.search(r"V\d+\.\d+", m)), None)


def _track(msgs: _Messages, path: Path, instance: int) -> Track:
    meta = head_meta(msgs, path, instance, compass_instances(msgs))
    streams = [_mag(msgs, path, meta, instance)]
    imu = _imu(msgs, path, meta)
    if imu is not None:
        streams.append(imu)
    streams += slow_streams(msgs, path, meta, baro="temp" not in (imu.columns if imu else {}))
    compass_meta(msgs, int(meta["compass_params_index"]), meta)
    streams = drop_nonfinite(streams, meta)
    if not any(len(s.t) for s in streams if "mx" in s.columns):
        raise InputError(f"{path}: no intact MAG message of compass {instance} "
                         f"({meta.get('read_warnings', 'all damaged')})")
    t0 = min(float(s.t.min()) for s in streams if len(s.t))
    meta["time_origin"] = f"log time {t0:.6f} s since boot is t = 0"
    meta["log_t0_s"] = f"{t0:.6f}"
    meta["messages"] = ", ".join(f"{s.name} {len(s.t)}" for s in streams)
    return merge(streams, meta, t0=t0)
