"""The message framing of a ULog file, checked before pyulog parses it: a damaged stretch is cut
out so that reading resumes at the next valid message (pyulog alone resumes only at a sync
message, and a damaged header that announces a long message ends its reading), and what was
lost is counted.

A ULog message is ``uint16 size, uint8 type`` then ``size`` bytes. A message is *plausible*
when its type is known, it fits in the file and its payload has the shape of that type (a data
message names a subscribed message id and has the size earlier messages of that id had; a
definition's key is printable text). After a message that is not plausible the next start is
the first offset where a plausible message is followed by another plausible one (or by the end
of the file).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

HEADER_BYTES = 16
#: ULog message types (flag bits, format, info, info multiple, parameter, parameter default,
#: subscription, unsubscription, data, logging, tagged logging, sync, dropout).
MESSAGE_TYPES = frozenset(b"BFIMPQARDLCSO")
SYNC_MAGIC = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"
#: incompat_flags[0] bit of the flag bits message: data appended at ``appended_offsets``.
DATA_APPENDED = 0x01
#: Smallest payload of each type (bytes); the exact size where it is fixed.
_MIN_SIZE = {ord("B"): 40, ord("A"): 4, ord("D"): 10, ord("L"): 9, ord("C"): 11,
             ord("I"): 3, ord("P"): 3, ord("M"): 4, ord("Q"): 4, ord("F"): 3}
_EXACT_SIZE = {ord("S"): 8, ord("O"): 2, ord("R"): 2}
_TYPE_LOOKUP = np.zeros(256, bool)
_TYPE_LOOKUP[list(MESSAGE_TYPES)] = True
_SCAN_WINDOW = 1 << 16


def _text(raw: bytes) -> bool:
    return bool(raw) and all(32 <= c < 127 for c in raw)


def _utf8(raw: bytes) -> bool:
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


@dataclass
class Framing:
    """``end``: the end of the last valid message (what follows is a cut tail); ``skipped``:
    ``(offset, bytes)`` of each damaged stretch cut out before it; ``spans``: the ``(start,
    stop)`` byte ranges kept."""

    end: int = HEADER_BYTES
    skipped: list = field(default_factory=list)
    spans: list = field(default_factory=list)
    _ids: dict = field(default_factory=dict)   # subscribed msg_id -> size of its data (or None)
    # (data, offset, length): the look-ahead of the last accepted message, which is what
    # plausible() gives at that offset as long as nothing is taken in between
    _ahead: tuple = (None, -1, 0)

    def plausible(self, data: bytes, at: int) -> int:
        """The length of the plausible message at ``at`` (header included), else 0."""
        if at + 3 > len(data):
            return 0
        size, kind = struct.unpack_from("<HB", data, at)
        stop = at + 3 + size
        if kind not in MESSAGE_TYPES or stop > len(data) or size < _MIN_SIZE.get(kind, 0) \
                or _EXACT_SIZE.get(kind, size) != size:
            return 0
        p = at + 3
        if kind == ord("D"):
            (msg_id,) = struct.unpack_from("<H", data, p)
            if msg_id not in self._ids or self._ids[msg_id] not in (None, size):
                return 0
        elif kind == ord("B"):
            return 3 + size if at == HEADER_BYTES else 0
        elif kind == ord("S"):
            return 3 + size if data[p:stop] == SYNC_MAGIC else 0
        elif kind == ord("A"):
            return 3 + size if _text(data[p + 3:stop]) else 0
        elif kind == ord("F"):
            return 3 + size if b":" in data[p:stop] and _text(data[p:stop]) else 0
        elif kind in b"LC":   # a log level '0'..'7', then text after the header fields
            text = data[p + (11 if kind == ord("C") else 9):stop]
            return 3 + size if 0x30 <= data[p] <= 0x37 and _utf8(text) else 0
        elif kind in b"IPMQ":
            key_at = p + (1 if kind in b"IP" else 2)
            n = data[key_at - 1]
            return 3 + size if key_at + n <= stop and b" " in data[key_at:key_at + n] \
                and _text(data[key_at:key_at + n]) else 0
        return 3 + size

    def take(self, data: bytes, at: int, n: int) -> None:
        """Count the message of ``n`` bytes at ``at`` as read (a subscription, a data size)."""
        kind = data[at + 2]
        if kind == ord("A"):
            (msg_id,) = struct.unpack_from("<H", data, at + 4)
            self._ids[msg_id] = None
        elif kind == ord("D"):
            (msg_id,) = struct.unpack_from("<H", data, at + 3)
            self._ids[msg_id] = n - 3

    def first_data(self, data: bytes, at: int) -> bool:
        """Whether the message at ``at`` is the first data message of its (subscribed) id."""
        return data[at + 2] == ord("D") and \
            self._ids.get(struct.unpack_from("<H", data, at + 3)[0], 0) is None

    def accept(self, data: bytes, at: int) -> int:
        """The length of the message at ``at`` when it is plausible and so is what follows it
        (a plausible message, the end of the file, or a last message the file's end cuts),
        counted as read (:meth:`take`); else 0, nothing counted."""
        seen, where, n = self._ahead
        if seen is not data or where != at:
            n = self.plausible(data, at)
        self._ahead = (None, -1, 0)
        if not n:
            return 0
        changes = data[at + 2] == ord("A") or self.first_data(data, at)
        saved = dict(self._ids) if changes else None
        self.take(data, at, n)
        nxt = at + n
        ahead = self.plausible(data, nxt)
        if nxt == len(data) or ahead or self._cut_at(data, nxt):
            self._ahead = (data, nxt, ahead)
            return n
        if saved is not None:
            self._ids = saved
        return 0

    @staticmethod
    def _cut_at(data: bytes, at: int) -> bool:
        """Whether a message of a known type starts at ``at`` and the file ends inside it."""
        if at + 3 > len(data):
            return True
        size, kind = struct.unpack_from("<HB", data, at)
        return kind in MESSAGE_TYPES and at + 3 + size > len(data)

    def resume(self, data: bytes, at: int) -> int | None:
        """The first offset from ``at`` where a message is accepted (:meth:`accept`, counted as
        read); None when there is none."""
        arr = np.frombuffer(data, np.uint8)
        while at + 3 <= len(data):
            window = arr[at + 2:at + 2 + _SCAN_WINDOW]
            for k in np.flatnonzero(_TYPE_LOOKUP[window]):
                p = at + int(k)
                if p + 3 <= len(data) and self.accept(data, p):
                    return p
            at += len(window)
        return None


def framing(data: bytes) -> Framing:
    """Walk the messages of ``data`` (a whole ULog file) from the end of its header."""
    out = Framing()
    at = start = HEADER_BYTES
    while at + 3 <= len(data):
        n = out.accept(data, at)
        if n:
            at += n
            out.end = at
            continue
        nxt = out.resume(data, at + 1)
        if nxt is None:
            break
        out.spans.append((start, at))
        out.skipped.append((at, nxt - at))
        start = nxt
        at = out.end = nxt + out.plausible(data, nxt)
    out.spans.append((start, out.end))
    return out


def kept_bytes(data: bytes, f: Framing) -> bytes:
    """The file with the damaged stretches and the cut tail left out; the flag bits message's
    appended-data offsets are moved with the bytes they point at (:func:`moved_offset`)."""
    if not f.skipped:
        return data[:f.end]
    return _with_appended_offsets(data[:HEADER_BYTES] + b"".join(data[a:b] for a, b in f.spans),
                                  f)


def moved_offset(offset: int, f: Framing) -> int:
    """Where the byte at file ``offset`` is in :func:`kept_bytes`' output: before the next kept
    byte when it was cut out (a damaged stretch, or the cut tail: then the output's end)."""
    at = HEADER_BYTES
    if offset < at:
        return offset
    for start, stop in f.spans:
        if offset < start:
            return at
        if offset <= stop:
            return at + offset - start
        at += stop - start
    return at


def _with_appended_offsets(kept: bytes, f: Framing) -> bytes:
    """``kept`` with the appended-data offsets of its flag bits message (ULog: incompat_flags[0]
    bit 0, then up to three uint64 file offsets where appended data starts; a reader seeks
    there, so an offset left pointing at the uncut file lands inside a message) moved."""
    p = HEADER_BYTES + 3
    if len(kept) < p + _MIN_SIZE[ord("B")] or kept[HEADER_BYTES + 2] != ord("B") \
            or not kept[p + 8] & DATA_APPENDED:
        return kept
    offsets = struct.unpack_from("<3Q", kept, p + 16)
    moved = [moved_offset(o, f) if o else 0 for o in offsets]
    out = bytearray(kept)
    struct.pack_into("<3Q", out, p + 16, *moved)
    return bytes(out)
