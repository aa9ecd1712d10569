"""Bulk decoder of ArduPilot DataFlash ``.bin`` logs: one header walk, then numpy per message type.

Why hand-written: :class:`pymavlink.DFReader.DFReader_binary` builds a Python object per
message (``_parse_next``, ``DFMessage.__getattr__`` per field, ``_add_msg`` per message) and its
constructor makes a full extra pass (``init_clock``); on the 20-minute PXF log that is ~5 s of
the ~10 s convert + diagnose budget (issue #10). Here the message headers are walked once, the
byte offsets of each wanted type gathered, and each type decoded at once with a numpy structured
dtype built from its FMT format string (``np.frombuffer`` view of the gathered rows).

What it keeps from pymavlink (values are identical to ``DFMessage.__getattr__``; the
equivalence test compares whole Tracks on every real log and this table against pymavlink's
``DFReader.FORMAT_TO_STRUCT``):

* the format characters, their little-endian types and multipliers (``c C e E`` ×0.01 and
  ``L`` ×1e-7 applied as a division by ``1/mult``, as pymavlink does for accuracy; ``n N Z``
  strings decoded UTF-8, else ISO-8859-1, cut at the first NUL; ``a`` int16[32]; ``M`` int8);
* the FMT message itself (type 128, 89 bytes, ``BBnNZ`` = Type, Length, Name, Format, Columns;
  names decoded with ``errors="backslashreplace"``); the last FMT of a type defines it, and a
  name maps to the last type that FMT gave it (pymavlink's ``formats`` / ``name_to_id``);
* resynchronisation: bytes that do not start ``0xA3 0x95`` + a type already defined by an FMT
  are skipped up to the next such header (pymavlink's ``_parse_next``); each skipped run is
  reported (offset, bytes) instead of printed.

pymavlink's module is not imported here (its import costs ~0.5 s: ``mavutil``, ``lxml``).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

MAGIC = b"\xa3\x95"   # HEAD_BYTE1, HEAD_BYTE2 of every DataFlash message
FMT_TYPE, FMT_LENGTH = 0x80, 89  # the self-describing FMT message: type 128, 89 bytes
_FMT_BODY = struct.Struct("<BB4s16s64s")

#: format char → (numpy little-endian type, multiplier or None); mirrors pymavlink's
#: ``DFReader.FORMAT_TO_STRUCT`` (checked by tests/test_dataflash_bulk.py).
FORMATS = {
    "a": ("(32,)<i2", None), "b": ("i1", None), "B": ("u1", None), "g": ("<f2", None),
    "h": ("<i2", None), "H": ("<u2", None), "i": ("<i4", None), "I": ("<u4", None),
    "f": ("<f4", None), "n": ("S4", None), "N": ("S16", None), "Z": ("S64", None),
    "c": ("<i2", 0.01), "C": ("<u2", 0.01), "e": ("<i4", 0.01), "E": ("<u4", 0.01),
    "L": ("<i4", 1.0e-7), "d": ("<f8", None), "M": ("i1", None), "q": ("<i8", None),
    "Q": ("<u8", None),
}
STRINGS = set("nNZ")


def _text(raw: bytes) -> str:
    """pymavlink's ``DFMessage.__getattr__`` for a string field: UTF-8, else ISO-8859-1, then
    cut at the first NUL."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("ISO-8859-1")
    return text.split("\0", 1)[0]


def _fmt_text(raw: bytes) -> str:
    """pymavlink's ``null_term`` of an FMT field (``to_string``: backslash-replace bad bytes)."""
    return raw.decode(errors="backslashreplace").split("\0", 1)[0]


@dataclass
class Format:
    """One FMT message: message ``type`` id, ``name``, ``length`` (bytes, header included),
    ``format`` characters and ``columns`` names."""

    type: int
    name: str
    length: int
    format: str
    columns: list

    def bad_chars(self) -> str:
        return "".join(c for c in self.format if c not in FORMATS)

    def dtype(self) -> np.dtype:
        """Packed structured dtype of the message body (``length - 3`` bytes), one field
        ``f<i>`` per format character."""
        return np.dtype([(f"f{i}", FORMATS[c][0]) for i, c in enumerate(self.format)])


@dataclass
class Walk:
    """The message chain of a log: ``offsets[type]`` (int64 byte offsets of each message's
    header), ``formats[type]`` (last FMT of each type), ``name_to_type``, ``skipped``
    [(offset, bytes)] of runs resynchronised over, ``cut`` bytes of a message the file ends
    inside (0 if none) and ``trailing`` bytes after the last message that start no header."""

    offsets: dict = field(default_factory=dict)
    formats: dict = field(default_factory=dict)
    name_to_type: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    cut: int = 0
    trailing: int = 0


class Walker:
    """The message chain walked piece by piece: :meth:`feed` consecutive stretches of the file,
    each starting where the previous call said to resume; ``walk`` holds the formats, name map,
    skipped runs, ``cut`` and ``trailing`` found so far (identical to :func:`walk` of the whole
    file once the last stretch was fed with ``final=True``)."""

    def __init__(self):
        self.lengths = [0] * 256
        self.lengths[FMT_TYPE] = FMT_LENGTH
        self.walk = Walk()
        self.pos = 0                 # absolute offset where the next message must start

    def feed(self, data: bytes, base: int, final: bool) -> tuple[np.ndarray, np.ndarray, int]:
        """Walk ``data``, the file's bytes from absolute offset ``base`` (``final``: they run
        to the end of the file). Returns ``(offsets, types, resume)``: the messages found
        (offsets relative to ``data``, int64; their type ids, uint8) and the relative offset the
        next call must start from (the bytes from there are given again, then the next ones).

        The candidate headers (every ``0xA3 0x95``) are found with numpy; the Python loop only
        visits candidates (one per message plus the rare payload bytes that look like a header).
        """
        size = len(data)
        out, lengths = self.walk, self.lengths
        buf = np.frombuffer(data, dtype=np.uint8)
        cand = np.flatnonzero((buf[:-2] == 0xA3) & (buf[1:-1] == 0x95)) if size >= 3 else \
            np.zeros(0, dtype=np.int64)
        types = buf[cand + 2]
        keep, keep_types = [], []
        pos = self.pos - base        # relative; negative inside a skipped run begun earlier
        resume = None
        for c, t in zip(cand.tolist(), types.tolist()):
            if c < pos:
                continue  # header-like bytes inside a message already taken
            length = lengths[t]
            if not length:
                continue  # unknown type: not a message start, keep scanning
            if c + length > size:
                if not final:
                    resume = c   # the message runs into the next stretch
                    break
                if c > pos:
                    out.skipped.append((base + pos, c - pos))
                out.cut = size - c
                pos = size
                break
            if c > pos:
                out.skipped.append((base + pos, c - pos))
            if t == FMT_TYPE:
                ftype, flen, name, fmt, cols = _FMT_BODY.unpack_from(data, c + 3)
                if flen >= 3:
                    lengths[ftype] = flen
                    fmt_obj = Format(ftype, _fmt_text(name), flen, _fmt_text(fmt),
                                     [col for col in _fmt_text(cols).split(",") if col] or [])
                    out.formats[ftype] = fmt_obj
                    out.name_to_type[fmt_obj.name] = ftype
            keep.append(c)
            keep_types.append(t)
            pos = c + length
        self.pos = base + pos
        if not final:
            if resume is None:   # the last 2 bytes were not examined as header starts
                resume = min(max(pos, size - 2), size)
            return np.asarray(keep, dtype=np.int64), np.asarray(keep_types, dtype=np.uint8), \
                max(resume, 0)
        if pos < size:
            if size - pos >= 2 and data[size - 2:] == MAGIC:  # the file ends inside a header
                if size - 2 > pos:
                    out.skipped.append((base + pos, size - 2 - pos))
                out.cut = 2
            else:
                out.trailing = size - pos
            self.pos = base + size
        return np.asarray(keep, dtype=np.int64), np.asarray(keep_types, dtype=np.uint8), size


def walk(data: bytes) -> Walk:
    """Follow the message chain of a whole file from byte 0 (see the module docstring for the
    rules); ``offsets[type]`` the messages of each type."""
    walker = Walker()
    offsets, kinds, _ = walker.feed(data, 0, final=True)
    out = walker.walk
    for t in np.unique(kinds).tolist():
        out.offsets[t] = offsets[kinds == t]
    return out


def decode(data: bytes, fmt: Format, offsets: np.ndarray) -> dict:
    """Columns of the messages of one type at ``offsets``: ``{column: array}`` with the values
    ``DFMessage.__getattr__`` returns: numeric fields float64 (multipliers applied), strings an
    object array of ``str``, ``a`` fields (n, 32) int16.

    Raises ValueError when the FMT's format has a character pymavlink does not know or its
    size is not the FMT's length − 3.
    """
    bad = fmt.bad_chars()
    if bad:
        raise ValueError(f"unsupported format character(s) {bad!r} in FMT of {fmt.name}")
    dtype = fmt.dtype()
    if dtype.itemsize != fmt.length - 3:
        raise ValueError(f"FMT of {fmt.name}: format {fmt.format!r} is {dtype.itemsize} bytes "
                         f"but the message length is {fmt.length} − 3 header bytes")
    buf = np.frombuffer(data, dtype=np.uint8)
    # each message's payload through a strided window view: no (n, itemsize) index array
    rows = (np.lib.stride_tricks.sliding_window_view(buf, dtype.itemsize)[offsets + 3]
            if len(offsets) else np.empty((0, dtype.itemsize), np.uint8))
    rec = np.ascontiguousarray(rows).view(dtype).reshape(len(offsets))
    out = {}
    for i, column in enumerate(fmt.columns[:len(fmt.format)]):
        char = fmt.format[i]
        values = rec[f"f{i}"]
        if char in STRINGS:
            out[column] = np.array([_text(v) for v in values.tolist()], dtype=object)
        elif char == "a":
            out[column] = values.astype(np.int16)
        else:
            with np.errstate(invalid="ignore", over="ignore"):   # damaged bytes: NaN, inf
                values = values.astype(np.float64)
            mult = FORMATS[char][1]
            if mult is not None:  # pymavlink divides by 1/mult (more accurate than × mult)
                values = values / (1 / mult) if 0.0 < mult < 1.0 else values * mult
            out[column] = values
    return out
