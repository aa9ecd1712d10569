"""A ULog with data appended after a cut (the flag bits message's appended-data offsets, as a
crash dump is appended to a log that stopped inside a message) stays readable when
streamcal.inputs.ulog_framing cuts damaged stretches out: the offsets are moved with the bytes
they point at, so the appended section is read as in the undamaged file."""
from __future__ import annotations

import io
import struct

import numpy as np
import pytest
from pyulog import ULog

from streamcal.inputs.ulog_framing import HEADER_BYTES, framing, kept_bytes, moved_offset

from ._selfmade_logs import _umsg, flight_slice, ulog_bytes

APPENDED_ID = 9          # a msg_id the main section does not use
N_APPENDED = 50


def _appended_log(cut: int = 10) -> tuple[bytes, int]:
    """A self-made ULog that stops ``cut`` bytes into a data message, then an appended section
    (its own subscription: sensor_mag instance 1, N_APPENDED samples, a logged text) at the
    offset the flag bits message names. (file bytes, the appended offset)."""
    main = bytearray(ulog_bytes(flight_slice(20.0)))
    last_data = main.rindex(b"D", 0, len(main) - 40) - 2      # any message: a header to cut
    main += main[last_data:last_data + cut]
    offset = len(main)
    main[HEADER_BYTES + 3 + 8] |= 0x01                         # incompat_flags[0]: DATA_APPENDED
    struct.pack_into("<Q", main, HEADER_BYTES + 3 + 16, offset)
    appended = [_umsg(b"A", struct.pack("<BH", 1, APPENDED_ID) + b"sensor_mag")]
    for k in range(N_APPENDED):
        us = 30_000_000 + 10_000 * k
        appended.append(_umsg(b"D", struct.pack("<HQIffff", APPENDED_ID, us, 1, 0.1 * k,
                                                 0.2, 0.3, 25.0)))
    appended.append(_umsg(b"L", b"3" + struct.pack("<Q", 31_000_000) + b"appended after the cut"))
    return bytes(main) + b"".join(appended), offset


def _appended_section(data: bytes) -> tuple[np.ndarray, list[str]]:
    """pyulog's reading of the appended section: sensor_mag instance 1's x, the logged texts."""
    ulog = ULog(io.BytesIO(data))
    x = [d.data["x"] for d in ulog.data_list if d.name == "sensor_mag" and d.multi_id == 1]
    return (x[0] if x else np.array([])), [m.message for m in ulog.logged_messages]


def _damaged(data: bytes, at: int, n: int = 300) -> bytes:
    out = bytearray(data)
    out[at:at + n] = np.random.default_rng(3).integers(0, 256, n, dtype=np.uint8).tobytes()
    return bytes(out)


def test_the_appended_section_reads_whole_from_the_uncut_file():
    data, offset = _appended_log()
    x, texts = _appended_section(data)
    assert len(x) == N_APPENDED and "appended after the cut" in texts
    # framing cuts the stopped message out: the offset moves back by its bytes
    f = framing(data)
    assert [n for _, n in f.skipped] == [10] and moved_offset(offset, f) == offset - 10
    x, texts = _appended_section(kept_bytes(data, f))
    assert len(x) == N_APPENDED and "appended after the cut" in texts


@pytest.mark.parametrize("where", [0.3, 0.6])
def test_a_damaged_stretch_before_the_appended_data_moves_its_offset(where):
    data, offset = _appended_log()
    bad = _damaged(data, int(where * offset))
    f = framing(bad)
    assert len(f.skipped) == 2 and sum(n for _, n in f.skipped) >= 310
    kept = kept_bytes(bad, f)
    (moved,) = [o for o in struct.unpack_from("<3Q", kept, HEADER_BYTES + 3 + 16) if o]
    assert moved == offset - sum(n for _, n in f.skipped)
    assert kept[moved:moved + 3] == data[offset:offset + 3]   # the appended section's first header
    x, texts = _appended_section(kept)
    np.testing.assert_array_equal(x, np.float32([0.1 * k for k in range(N_APPENDED)]))
    assert "appended after the cut" in texts


def test_an_offset_inside_a_cut_stretch_moves_to_the_next_kept_byte():
    data, offset = _appended_log()
    bad = _damaged(data, offset - 100, 110)          # the appended section's start is damaged
    f = framing(bad)
    start, n = f.skipped[-1]
    assert start < offset < start + n
    assert moved_offset(offset, f) == moved_offset(start + n, f)
    x, _ = _appended_section(kept_bytes(bad, f))      # read on, whatever the damage left
    assert len(x) <= N_APPENDED


def test_a_log_without_appended_data_keeps_its_flag_bits():
    data = ulog_bytes(flight_slice(20.0))
    bad = _damaged(data, len(data) // 2)
    f = framing(bad)
    kept = kept_bytes(bad, f)
    assert f.skipped and kept[HEADER_BYTES:HEADER_BYTES + 43] == data[HEADER_BYTES:HEADER_BYTES + 43]
