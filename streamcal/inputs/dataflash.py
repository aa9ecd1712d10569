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
BAT    Volt, Curr (newer firmware)       as CURR
BARO   Temp °C                           ``temp`` when IMU has no temperature (said so)
PARM   Name, Value                       COMPASS_* in the metadata (``param.NAME``)
====== ================================ ==================================================

Time is ``TimeUS`` (µs) or ``TimeMS`` (ms), shifted to start at 0 s; each message is its own row.
Only instance 0 of MAG and IMU is read (a field ``I`` names the instance in newer layouts).

ArduPilot logs the *corrected* field: with COMPASS_OFS = ``o`` (added, ``AP_Compass``), motor
offsets ``MOfs`` and the soft-iron matrix ``S`` of COMPASS_DIA/ODI, ``MAG = S (raw + o) + MOfs``
(offsets → matrix → motor, the order of ``AP_Compass_Backend::correct_field``). The reader
returns ``raw = S⁻¹ (MAG − MOfs) − o`` with ``o`` and ``MOfs`` taken per sample from the MAG
message itself, and says in the metadata what it undid.
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
from .autopilot_cal import COMPASS_PARAMS, MG_PER_UT, ardupilot_matrix
from .streams import Stream, merge
from .dataflash_bulk import MAGIC, decode, walk
from .attitude_streams import DATAFLASH_MESSAGES, dataflash_attitude

MESSAGES = ("MAG", "IMU", "RCOU", "CURR", "BAT", "BARO", "PARM", "MSG")
MESSAGES += DATAFLASH_MESSAGES  # attitude and GPS: .attitude_streams
#: PWM outputs are 0 (off/unused) or roughly 800–2200 µs; anything outside this is not PWM.
PWM_RANGE_US = (0.0, 3000.0)
#: CURR.Throttle / ThrOut run 0..1000 in the firmware versions that log them.
THROTTLE_FULL = 1000.0
#: Integer-typed CURR Volt/Curr fields are centivolts / centiamps (older layouts).
CENTI = 0.01
_INT_TYPES = set("bBhHiIqQ")


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


def _refuse_cut(path: Path, left: int, skip_bad_rows: bool) -> None:
    if left > 0 and not skip_bad_rows:
        raise InputError(f"{path}: DataFlash log ends inside a message (its last {left} bytes): "
                         "the file is truncated or damaged (--skip-bad-rows reads the complete "
                         "messages)")


def _parse(path: Path, skip_bad_rows: bool) -> _Messages:
    """The wanted messages, decoded in bulk (:mod:`.dataflash_bulk`)."""
    data = _read_bytes(path)
    chain = walk(data)
    _refuse_cut(path, chain.cut, skip_bad_rows)
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
            for key, value in zip(cols["Name"].tolist(), cols["Value"].tolist()):
                out.params[str(key)] = float(value)
        elif name == "MSG" and "Message" in cols:
            out.texts += [str(m) for m in cols["Message"].tolist()]
        elif name not in ("PARM", "MSG"):
            out.fields[name] = list(fmt.columns)
            out.cols[name] = cols
            out.types[name] = dict(zip(fmt.columns, fmt.format))
    if chain.cut > 0:
        out.texts.append(f"truncated: {chain.cut} trailing bytes ignored")
    if chain.skipped:
        runs = ", ".join(f"{n} at offset {at}" for at, n in chain.skipped[:5])
        more = f" and {len(chain.skipped) - 5} more runs" if len(chain.skipped) > 5 else ""
        out.texts.append(f"Skipped {sum(n for _, n in chain.skipped)} bad bytes ({runs}{more}): "
                         "resynchronised on the next message header")
    if chain.trailing:
        out.texts.append(f"Skipped {chain.trailing} trailing bytes after the last message "
                         "(no message header)")
    return out


def _parse_pymavlink(path: Path, skip_bad_rows: bool) -> _Messages:
    """The same through :class:`pymavlink.DFReader.DFReader_binary` (an object per message,
    ~10× slower): the reference the equivalence test compares :func:`_parse` against."""
    from pymavlink import DFReader  # heavy (lxml, ~0.5 s): imported only when asked for

    cut = walk(_read_bytes(path)).cut
    _refuse_cut(path, cut, skip_bad_rows)
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
        out.texts.append(f"truncated: {cut} trailing bytes ignored")
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


def _instance0(msgs: _Messages, name: str) -> None:
    """Keep the rows of instance 0 when the layout has an instance field ``I``."""
    if msgs.has(name, "I"):
        keep = msgs.array(name, "I") == 0
        msgs.cols[name] = {k: v[keep] for k, v in msgs.cols[name].items()}


def _mag(msgs: _Messages, path: Path, meta: dict) -> Stream:
    if not msgs.count("MAG"):
        raise InputError(f"{path}: no MAG messages: this log has no magnetometer data "
                         f"(messages found: {', '.join(sorted(msgs.cols)) or 'none'})")
    if not msgs.has("MAG", "MagX", "MagY", "MagZ"):
        raise InputError(f"{path}: MAG message without MagX/MagY/MagZ (fields: "
                         f"{', '.join(msgs.fields['MAG'])}): unknown layout")
    _instance0(msgs, "MAG")
    t = _time(msgs, "MAG", path)
    logged = np.column_stack([msgs.array("MAG", c) for c in ("MagX", "MagY", "MagZ")])
    meta["autopilot_field_uT"] = f"{np.median(np.linalg.norm(logged, axis=1)) / MG_PER_UT:.4g}"
    raw = logged.copy()
    if msgs.has("MAG", "MOfsX", "MOfsY", "MOfsZ"):
        mofs = np.column_stack([msgs.array("MAG", c) for c in ("MOfsX", "MOfsY", "MOfsZ")])
        raw -= mofs
        meta["mag_motor_offsets_undone"] = (
            "MAG.MOfsX/Y/Z subtracted per sample" if np.any(mofs) else "none (MAG.MOfs all 0)")
    else:
        mofs = None
        meta["mag_motor_offsets_undone"] = "could not: MAG has no MOfsX/Y/Z"
    S = ardupilot_matrix(msgs.params)
    if np.allclose(S, np.eye(3)):
        meta["mag_soft_iron_undone"] = "none (COMPASS_DIA/ODI identity or not logged)"
    else:
        raw = np.linalg.solve(S, raw.T).T
        meta["mag_soft_iron_undone"] = "inverse of the PARM COMPASS_DIA/ODI matrix applied" + (
            " (assumes motor offsets added after the matrix, ArduPilot 4.x order)"
            if mofs is not None and np.any(mofs) else "")
    if msgs.has("MAG", "OfsX", "OfsY", "OfsZ"):
        ofs = np.column_stack([msgs.array("MAG", c) for c in ("OfsX", "OfsY", "OfsZ")])
        raw -= ofs
        values = np.unique(ofs, axis=0)
        shown = ",".join(f"{v:g}" for v in values[0]) if len(values) == 1 else \
            f"{len(values)} different sets over the log"
        meta["mag_offsets_undone"] = (f"MAG.OfsX/Y/Z subtracted per sample (ArduPilot adds "
                                      f"them: logged = raw + Ofs); Ofs = {shown} mG")
    elif all(f"COMPASS_OFS_{a}" in msgs.params for a in "XYZ"):
        ofs = np.array([msgs.params[f"COMPASS_OFS_{a}"] for a in "XYZ"])
        raw -= ofs
        meta["mag_offsets_undone"] = ("PARM COMPASS_OFS_X/Y/Z subtracted (MAG has no OfsX/Y/Z; "
                                      f"assumed constant) = {','.join(f'{v:g}' for v in ofs)} mG")
    else:
        meta["mag_offsets_undone"] = ("could not: MAG has no OfsX/Y/Z and no COMPASS_OFS_* "
                                      "parameter was logged; mx,my,mz are the corrected field")
    mag = raw / MG_PER_UT
    return Stream("MAG", t, {"mx": mag[:, 0], "my": mag[:, 1], "mz": mag[:, 2]})


def _imu(msgs: _Messages, path: Path, meta: dict) -> Stream | None:
    names = ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ")
    if not msgs.has("IMU", *names) or not msgs.count("IMU"):
        return None
    _instance0(msgs, "IMU")
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
    _instance0(msgs, "BARO")
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


def _battery(msgs: _Messages, path: Path, meta: dict) -> list[Stream]:
    out = []
    for name in ("CURR", "BAT"):
        if not msgs.count(name):
            continue
        _instance0(msgs, name)
        types = msgs.types.get(name, {})
        cols = {}
        for field_name, label in (("Volt", "battery_voltage_v"), ("Curr", "battery_current_a")):
            if msgs.has(name, field_name):
                scale = CENTI if types.get(field_name) in _INT_TYPES else 1.0
                cols[label] = msgs.array(name, field_name) * scale
        for field_name in ("Throttle", "ThrOut"):
            if msgs.has(name, field_name):
                cols["throttle"] = msgs.array(name, field_name) / THROTTLE_FULL
                meta["throttle_source"] = f"{name}.{field_name} / {THROTTLE_FULL:g} (0..1)"
                break
        constant = [k for k, v in cols.items() if np.all(v == v[0])]
        for k in constant:
            del cols[k]
        if constant:
            meta[f"{name.lower()}_constant_dropped"] = ",".join(constant) + \
                " (constant over the log: no sensor fitted or not logged)"
        if cols:
            out.append(Stream(name, _time(msgs, name, path), cols))
    return out


def read_dataflash(path, *, skip_bad_rows: bool = False) -> Track:
    """Read an ArduPilot DataFlash ``.bin`` log into a Track (see the module docstring).

    Raises :class:`InputError` naming the file and the message when the log is truncated
    (unless ``skip_bad_rows``), has no MAG messages or a layout without the needed fields.
    """
    path = Path(path)
    return _track(_parse(path, skip_bad_rows), path)


def read_dataflash_pymavlink(path, *, skip_bad_rows: bool = False) -> Track:
    """:func:`read_dataflash` with the messages decoded by pymavlink's DFReader instead of the
    bulk decoder (much slower): the reference of the equivalence test and the read benchmark."""
    path = Path(path)
    return _track(_parse_pymavlink(path, skip_bad_rows), path)


def _track(msgs: _Messages, path: Path) -> Track:
    meta = {"sensor": "ardupilot compass (instance 0)", "source": f"ArduPilot DataFlash log {path.name}",
            "input_format": "ardupilot-dataflash", "mag_unit": "uT",
            "mag_axes": "body frame (ArduPilot rotates by COMPASS_ORIENT/AHRS_ORIENTATION "
                        "before logging)",
            "units": "mx,my,mz uT (from mG /10); ax,ay,az m/s^2; gx,gy,gz rad/s; temp degC; "
                     "rcou_c* us; battery_current_a A; battery_voltage_v V; throttle 0..1"}
    firmware = next((m for m in msgs.texts if re.search(r"V\d+\.\d+", m)), None)
    if firmware:
        meta["firmware"] = firmware
    streams = [_mag(msgs, path, meta)]
    imu = _imu(msgs, path, meta)
    if imu is not None:
        streams.append(imu)
    if "temp" not in (imu.columns if imu else {}):
        baro = _baro_temp(msgs, path, meta)
        if baro is not None:
            streams.append(baro)
    rcou = _rcou(msgs, path, meta)
    if rcou is not None:
        streams.append(rcou)
    streams += _battery(msgs, path, meta)
    streams += dataflash_attitude(msgs, lambda name: _time(msgs, name, path), meta)
    for name, value in msgs.params.items():
        if COMPASS_PARAMS.fullmatch(name):
            meta[f"param.{name}"] = f"{value:g}"
    notes = [m for m in msgs.texts if m.startswith(("truncated", "Skipped"))]
    if notes:
        meta["read_warnings"] = "; ".join(notes)
    t0 = min(float(s.t.min()) for s in streams if len(s.t))
    meta["time_origin"] = f"log time {t0:.6f} s since boot is t = 0"
    meta["messages"] = ", ".join(f"{s.name} {len(s.t)}" for s in streams)
    return merge(streams, meta, t0=t0)
