"""The bulk DataFlash decoder against pymavlink: same Track on every real log, same format table;
damaged logs resynchronised on the next header and the skipped bytes named."""
import functools
import struct

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.inputs import dataflash
from streamcal.inputs.dataflash_bulk import FORMATS

from ._shared_checks import (check_bulk_track_equals_pymavlink_track,
                             check_damaged_message_resynchronised,
                             check_garbage_run_skipped_and_named, check_random_damage,
                             check_string_where_a_number_is_needed_named,
                             check_unknown_format_character_named,
                             check_walk_follows_every_message, cut_inside_header_and_body)
from .test_inputs_flight import BINS

PXF = BINS[1]


@pytest.mark.slow
@pytest.mark.parametrize("name", BINS)
def test_bulk_track_equals_pymavlink_track(flight_dir, name):
    """Every column (time included), every metadata entry: the bulk decoder and pymavlink's
    DFReader give the same Track."""
    check_bulk_track_equals_pymavlink_track(flight_dir / name)


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


def test_walk_follows_every_message_of_a_clean_log(flight_dir):
    check_walk_follows_every_message(flight_dir / PXF)


def test_garbage_run_skipped_and_named(flight_dir, tmp_path):
    """A run of foreign bytes between two messages (one looks like a header of an unknown type):
    every message is still read, as pymavlink reads them, and read_warnings names the run."""
    check_garbage_run_skipped_and_named(flight_dir / PXF, tmp_path)


def test_damaged_message_resynchronised(flight_dir, tmp_path):
    """5 bytes lost inside message j: j is read over the start of j + 1 (there is no checksum),
    the rest of j + 1 is skipped up to the next header, every other message is read."""
    check_damaged_message_resynchronised(flight_dir / PXF, tmp_path)


def test_truncated_inside_header_and_body(flight_dir, tmp_path, capsys):
    """A log cut inside a header or a body (a crash, a power cut) is read to its last complete
    message: what was lost is in read_warnings and on one stderr line, exit 0."""
    for cut, track in cut_inside_header_and_body(flight_dir / PXF, tmp_path):
        whole = dataflash.read_dataflash(flight_dir / PXF)
        assert 0 < len(track.t_mag) < len(whole.t_mag)
    assert main(["convert", str(cut), "-o", str(tmp_path / "o.csv")]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if str(cut) in line]
    assert len(err) == 1 and "lost: truncated: 7 trailing bytes" in err[0]


def test_unknown_format_character_named(flight_dir, tmp_path):
    """An FMT whose format has a character pymavlink does not know: unknown layout, named."""
    check_unknown_format_character_named(flight_dir / PXF, tmp_path)


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
    check_string_where_a_number_is_needed_named(flight_dir / PXF, tmp_path, b"QhhhhhhhhhB")


@functools.lru_cache(maxsize=1)
def _head(flight_dir):
    return (flight_dir / BINS[2]).read_bytes()[:120_000]


@pytest.mark.parametrize("seed", range(12))
def test_random_damage_gives_a_track_or_a_named_error(flight_dir, tmp_path, seed):
    """Flipped, inserted and deleted bytes (mostly in the FMT block): the reader returns a Track
    or raises InputError naming the file, never another exception."""
    check_random_damage(_head(flight_dir), tmp_path, seed, fmt_block=8000)
