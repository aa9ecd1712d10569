"""The bulk DataFlash decoder against pymavlink: same Track on every real log, same format table;
damaged logs resynchronised on the next header and the skipped bytes named."""
import functools
import struct

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.errors import InputError
from streamcal.inputs import dataflash
from streamcal.inputs.dataflash_bulk import FMT_TYPE, FORMATS, walk

from .test_inputs_flight import BINS

PXF = BINS[1]


def _assert_same_track(a, b, *, metadata=True):
    assert list(a.columns) == list(b.columns)
    for name in a.columns:
        np.testing.assert_array_equal(a.columns[name], b.columns[name], err_msg=name)
    if metadata:
        assert a.metadata == b.metadata
    assert len(a) == len(b) and a.skipped_rows == b.skipped_rows


@pytest.mark.slow
@pytest.mark.parametrize("name", BINS)
def test_bulk_track_equals_pymavlink_track(flight_dir, name):
    """Every column (time included), every metadata entry: the bulk decoder and pymavlink's
    DFReader give the same Track."""
    path = flight_dir / name
    bulk = dataflash.read_dataflash(path)
    reference = dataflash.read_dataflash_pymavlink(path)
    _assert_same_track(bulk, reference)
    assert len(bulk.t_mag) > 1000 and "read_warnings" not in bulk.metadata


def test_format_table_matches_pymavlink():
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    assert set(FORMATS) == set(FORMAT_TO_STRUCT)
    for char, (code, mult) in FORMATS.items():
        s, pm_mult, kind = FORMAT_TO_STRUCT[char]
        dtype = np.dtype(code)
        assert dtype.itemsize == struct.calcsize("<" + s), char
        assert mult == pm_mult, char
        if char in "nNZa":
            continue
        # same kind: decode the same bytes both ways
        raw = bytes(range(1, dtype.itemsize + 1))
        assert float(np.frombuffer(raw, dtype)[0]) == float(struct.unpack("<" + s, raw)[0]), char


def _messages(data):
    chain = walk(data)
    offsets = sorted((int(o), t) for t, offs in chain.offsets.items() for o in offs)
    return chain, offsets


def test_walk_follows_every_message_of_a_clean_log(flight_dir):
    data = (flight_dir / PXF).read_bytes()
    chain, offsets = _messages(data)
    assert offsets[0] == (0, FMT_TYPE) and not chain.skipped and chain.cut == 0
    ends = [o + chain.formats[t].length for o, t in offsets]
    assert ends[:-1] == [o for o, _ in offsets[1:]] and ends[-1] == len(data)  # back to back


def test_garbage_run_skipped_and_named(flight_dir, tmp_path):
    """A run of foreign bytes between two messages (one looks like a header of an unknown type):
    every message is still read, as pymavlink reads them, and read_warnings names the run."""
    data = (flight_dir / PXF).read_bytes()
    _, offsets = _messages(data)
    at = offsets[len(offsets) // 2][0]
    junk = b"\x00\x11\xa3\x95\xfe\x22" * 3
    bad = tmp_path / "junk.bin"
    bad.write_bytes(data[:at] + junk + data[at:])
    track = dataflash.read_dataflash(bad)
    warning = track.metadata["read_warnings"]
    assert f"Skipped {len(junk)} bad bytes ({len(junk)} at offset {at})" in warning
    clean = dataflash.read_dataflash(flight_dir / PXF)
    _assert_same_track(track, clean, metadata=False)


def test_damaged_message_resynchronised(flight_dir, tmp_path):
    """5 bytes lost inside message j: j is read over the start of j + 1 (there is no checksum),
    the rest of j + 1 is skipped up to the next header, every other message is read."""
    data = (flight_dir / PXF).read_bytes()
    chain, offsets = _messages(data)
    j = len(offsets) // 3
    (start, _), (nxt, ntype) = offsets[j], offsets[j + 1]
    bad = tmp_path / "cut_inside.bin"
    bad.write_bytes(data[:start + 10] + data[start + 15:])
    got_chain, got = _messages(bad.read_bytes())
    shift = [(o - 5 if o > start else o, t) for o, t in offsets]
    assert got == shift[:j + 1] + shift[j + 2:]
    lost = chain.formats[ntype].length - 5
    assert got_chain.skipped == [(nxt, lost)]
    track = dataflash.read_dataflash(bad)
    assert f"Skipped {lost} bad bytes ({lost} at offset {nxt})" in track.metadata["read_warnings"]


def test_truncated_inside_header_and_body(flight_dir, tmp_path, capsys):
    """A log cut inside a header or a body (a crash, a power cut) is read to its last complete
    message: what was lost is in read_warnings and on one stderr line, exit 0."""
    data = (flight_dir / PXF).read_bytes()
    _, offsets = _messages(data)
    last = offsets[len(offsets) // 2][0]
    for keep, left in ((last + 2, 2), (last + 7, 7)):
        cut = tmp_path / f"cut{keep}.bin"
        cut.write_bytes(data[:keep])
        track = dataflash.read_dataflash(cut)
        assert f"truncated: {left} trailing bytes ignored" in track.metadata["read_warnings"]
        whole = dataflash.read_dataflash(flight_dir / PXF)
        assert 0 < len(track.t_mag) < len(whole.t_mag)
    assert main(["convert", str(cut), "-o", str(tmp_path / "o.csv")]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if str(cut) in line]
    assert len(err) == 1 and "lost: truncated: 7 trailing bytes" in err[0]


def test_unknown_format_character_named(flight_dir, tmp_path):
    """An FMT whose format has a character pymavlink does not know: unknown layout, named."""
    data = bytearray((flight_dir / PXF).read_bytes())
    chain, offsets = _messages(bytes(data))
    mag = next(o for o, t in offsets if t == FMT_TYPE and chain.formats[data[o + 3]].name == "MAG")
    fmt_at = mag + 3 + 1 + 1 + 4  # header, Type, Length, Name → Format
    data[fmt_at + 1] = ord("X")
    bad = tmp_path / "odd_fmt.bin"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"odd_fmt\.bin.*'X'.*MAG.*unknown layout"):
        dataflash.read_dataflash(bad)


def test_every_format_character_decodes_as_pymavlink_getattr():
    """Synthetic messages with every format character (random bytes; NUL-cut, non-UTF-8
    strings): each field equals what pymavlink's ``DFMessage.__getattr__`` returns, multipliers
    (c C e E L) included."""
    from pymavlink.DFReader import DFFormat, DFMessage

    from streamcal.inputs.dataflash_bulk import Format, decode

    chars = "abBghHiIfnNZcCeELdMqQ"
    columns = [f"F{c}{i}" for i, c in enumerate(chars)]
    pm = DFFormat(0x40, "TEST", 0, chars, ",".join(columns))
    size = struct.calcsize(pm.msg_struct)
    rng = np.random.default_rng(7)
    bodies = [rng.integers(0, 256, size, dtype=np.uint8).tobytes() for _ in range(200)]
    strings = [b"ab\0\xff", "é\0zz".encode() + b"\0" * 11, b"x" * 64]  # NUL cut; ISO-8859-1
    n_at = struct.calcsize("<" + "".join(
        {"a": "64s", "g": "e"}.get(c, c) for c in "abBghHiIf"))
    bodies[0] = bodies[0][:n_at] + strings[0] + strings[1] + strings[2] + bodies[0][n_at + 84:]
    data = b"".join(b"\xa3\x95\x40" + body for body in bodies)
    offsets = np.arange(len(bodies), dtype=np.int64) * (size + 3)
    got = decode(data, Format(0x40, "TEST", size + 3, chars, columns), offsets)
    for k, body in enumerate(bodies):
        msg = DFMessage(pm, list(struct.unpack(pm.msg_struct, body)), True, None)
        for i, column in enumerate(columns):
            want = getattr(msg, column)
            if chars[i] == "a":  # int16[32] over the 64 raw bytes pymavlink unpacks
                raw = struct.unpack(pm.msg_struct, body)[i]
                assert got[column][k].astype("<i2").tobytes() == raw, (column, k)
            elif isinstance(want, str):
                assert got[column][k] == want, (column, k)
            else:
                g = got[column][k]
                assert g == want or (np.isnan(g) and np.isnan(want)), (column, k, g, want)
    assert got["FZ11"][0] == "x" * 64 and got["Fn9"][0] == "ab"


def test_string_where_a_number_is_needed_named(flight_dir, tmp_path):
    data = bytearray((flight_dir / PXF).read_bytes())
    chain, offsets = _messages(bytes(data))
    mag = next(o for o, t in offsets if t == FMT_TYPE and chain.formats[data[o + 3]].name == "MAG")
    fmt_at = mag + 3 + 1 + 1 + 4
    assert data[fmt_at:fmt_at + 11] == b"QhhhhhhhhhB"  # the test is about this layout
    data[fmt_at:fmt_at + 11] = b"QnhhhhhhhB\0"  # same size: MagX, MagY become a 4-byte string
    bad = tmp_path / "string_mag.bin"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"string_mag\.bin: MAG\.MagX is not a number.*'n'"):
        dataflash.read_dataflash(bad)


@functools.lru_cache(maxsize=1)
def _head(flight_dir):
    return (flight_dir / BINS[2]).read_bytes()[:120_000]


@pytest.mark.parametrize("seed", range(12))
def test_random_damage_gives_a_track_or_a_named_error(flight_dir, tmp_path, seed):
    """Flipped, inserted and deleted bytes (mostly in the FMT block): the reader returns a Track
    or raises InputError naming the file, never another exception."""
    rng = np.random.default_rng(seed)
    blob = bytearray(_head(flight_dir))
    for _ in range(int(rng.integers(1, 25))):
        at = int(rng.integers(0, 8000 if rng.random() < 0.7 else len(blob)))
        op = rng.random()
        if op < 0.4:
            blob[at] ^= int(rng.integers(1, 256))
        elif op < 0.7:
            blob[at:at] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
        else:
            del blob[at:at + int(rng.integers(1, 9))]
    path = tmp_path / "damaged.bin"
    path.write_bytes(bytes(blob))
    for skip in (False, True):
        try:
            track = dataflash.read_dataflash(path, skip_bad_rows=skip)
        except InputError as exc:
            assert str(path) in str(exc)
        else:
            assert len(track.t_mag) > 0
