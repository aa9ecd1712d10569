"""A DataFlash log read piece by piece (streamcal.inputs.dataflash_chunks): its Tracks end to end
are the whole-log reader's Track, every column, row order and metadata entry, on self-made logs
of every layout, on damaged and cut ones, and on the real logs; the resumable header walk is the
whole walk."""
import numpy as np
import pytest

from streamcal.errors import InputError
from streamcal.inputs import dataflash, dataflash_chunks
from streamcal.inputs.dataflash_bulk import Walker, walk
from streamcal.inputs.track import Track

from ._dataflash_log import write_flight
from ._shared_checks import damaged
from ._selfmade_logs import flight_slice, write_dataflash
from .test_inputs_flight import BINS

PIECES = (1 << 12, 1 << 15)   # small pieces: many resumptions of the walk and of the merge


def _joined(chunks: list) -> Track:
    first = chunks[0]
    for c in chunks:
        assert list(c.columns) == list(first.columns) and c.metadata == first.metadata
    return Track({n: np.concatenate([c.columns[n] for c in chunks]) for n in first.columns},
                 first.metadata, first.path)


def check_chunks_are_the_whole_track(path, compass=None, *, streamed=True) -> int:
    """The pieces' Tracks end to end equal ``read_dataflash`` (metadata and its order included);
    ``streamed``: the log was read piece by piece, not whole then sliced. Returns the number of
    Tracks of the smallest piece size."""
    whole = dataflash.read_dataflash(path, compass=compass)
    n = 0
    for piece in PIECES:
        chunks = list(dataflash_chunks.iter_dataflash_chunks(path, compass=compass,
                                                             piece_bytes=piece))
        n = n or len(chunks)
        got = _joined(chunks)
        assert list(got.columns) == list(whole.columns)
        for name in whole.columns:
            np.testing.assert_array_equal(got.columns[name], whole.columns[name], err_msg=name)
        assert list(got.metadata.items()) == list(whole.metadata.items())
        assert all(c.path == path for c in chunks)
        if streamed:
            dataflash_chunks._survey(path, compass, piece)   # no fallback to the whole read
    return n


def _selfmade(tmp_path, name="flight.bin", seconds=40.0, **kw):
    return write_dataflash(tmp_path / name, flight_slice(seconds, seed=2), **kw)


@pytest.mark.parametrize("kw", [
    {},
    {"messages": ("IMU", "RCOU", "CURR")},
    {"messages": ("IMU", "BAT"), "motor_comp": np.array([40.0, -25.0, 60.0])},
    {"messages": ("RCOU",), "c7_not_pwm": True},
])
def test_selfmade_log_in_pieces_is_the_whole_track(tmp_path, kw):
    path = _selfmade(tmp_path, **kw)
    assert check_chunks_are_the_whole_track(path) > 3


@pytest.mark.parametrize("layout,throttle_in", [("old", "CTUN"), ("instance", "RCOU"),
                                                ("instance", ""), ("old", "RCOU")])
def test_several_compasses_in_pieces(tmp_path, layout, throttle_in):
    path = tmp_path / "three.bin"
    write_flight(path, [{"ofs": (30, -20, 10)}, {"ofs": (-5, 8, 40), "err": (20, 0, 0)},
                        {"err": (0, 0, 30)}], seconds=30.0, layout=layout,
                 throttle_in=throttle_in, motct=1, mot=(3.0, -2.0, 5.0),
                 extra_params={"COMPASS_PRIMARY": 1})
    for compass in (None, 0, 1, 2):
        check_chunks_are_the_whole_track(path, compass)


def test_damaged_and_cut_logs_in_pieces(tmp_path):
    """Garbage runs (one across a piece boundary), a message losing bytes, cuts inside a
    header and inside a message: the same Track and the same read_warnings as the whole read."""
    data = _selfmade(tmp_path, seconds=20.0).read_bytes()
    chain = walk(data)
    offsets = sorted(int(o) for offs in chain.offsets.values() for o in offs)
    junk = b"\x00\x11\xa3\x95\xfe\x22" * 3
    a, b, c = offsets[len(offsets) // 4], offsets[len(offsets) // 2], offsets[2 * len(offsets) // 3]
    variants = {
        "junk": data[:a] + junk + data[a:b] + junk * 900 + data[b:],
        "lost": data[:c + 9] + data[c + 14:],
        "cut_header": data[:b + 2], "cut_body": data[:b + 7],
        "trailing": data + b"\x01\x02\x03",
    }
    for name, blob in variants.items():
        path = tmp_path / f"{name}.bin"
        path.write_bytes(blob)
        check_chunks_are_the_whole_track(path)
        if name != "lost":   # a lost part of a message can merge into its neighbour silently
            assert dataflash.read_dataflash(path).metadata.get("read_warnings")


@pytest.mark.parametrize("seed", range(8))
def test_random_damage_in_pieces(tmp_path, seed):
    """Bytes flipped, inserted, deleted: a Track equal to the whole read's, or the same
    InputError."""
    blob = _selfmade(tmp_path, seconds=8.0).read_bytes()
    path = tmp_path / "damaged.bin"
    path.write_bytes(damaged(blob, np.random.default_rng(seed), 1200, 0.5))
    try:
        dataflash.read_dataflash(path)
    except InputError as exc:
        with pytest.raises(InputError) as err:
            list(dataflash_chunks.iter_dataflash_chunks(path, piece_bytes=PIECES[0]))
        assert str(err.value) == str(exc)
        return
    check_chunks_are_the_whole_track(path, streamed=False)


def test_walk_in_pieces_is_the_whole_walk(tmp_path):
    """Fed in stretches of any size, the walker finds the messages, formats, skipped runs, cut
    and trailing bytes of the whole walk."""
    data = _selfmade(tmp_path, seconds=5.0).read_bytes()
    half = len(data) // 2
    blob = data[:half] + b"\xa3\x95\x00" * 5 + b"junk" + data[half:-5]
    whole = walk(blob)
    every = np.sort(np.concatenate(list(whole.offsets.values())))
    for size in (7, 100, 4096, len(blob) + 1):
        walker, found, base = Walker(), [], 0
        carry = b""
        for start in range(0, len(blob) + size, size):
            block = blob[start:start + size]
            data_ = carry + block
            offs, _, resume = walker.feed(data_, base, final=not block)
            found.append(offs + base)
            if not block:
                break
            carry, base = data_[resume:], base + resume
        assert np.array_equal(np.sort(np.concatenate(found)), every)
        got = walker.walk
        assert (got.skipped, got.cut, got.trailing) == (whole.skipped, whole.cut, whole.trailing)
        assert got.formats == whole.formats and got.name_to_type == whole.name_to_type


def test_pieces_are_time_ordered_and_bounded(tmp_path):
    """Many Tracks, each in time order after the one before, none holding much more than a
    piece's worth of rows."""
    path = _selfmade(tmp_path, seconds=60.0)
    chunks = list(dataflash_chunks.iter_dataflash_chunks(path, piece_bytes=1 << 14))
    assert len(chunks) > 20
    rows_per_piece = (1 << 14) / 40   # messages are ≥ 20 bytes; 2 pieces' worth at most
    for before, after in zip(chunks, chunks[1:]):
        assert before.columns["t"][-1] <= after.columns["t"][0]
    assert max(len(c) for c in chunks) < 2 * rows_per_piece * 2
    one = list(dataflash_chunks.iter_dataflash_chunks(path, piece_bytes=path.stat().st_size))
    assert len(one) == 1 and len(one[0]) == sum(len(c) for c in chunks)   # read once, whole
    assert one[0].path == path and all(c.path == path for c in chunks)


@pytest.mark.slow
@pytest.mark.parametrize("name", BINS)
def test_real_log_in_pieces_is_the_whole_track(flight_dir, name):
    path = flight_dir / name
    for track in dataflash.read_dataflash_compasses(path):
        check_chunks_are_the_whole_track(path, int(track.metadata["compass_instance"]))


@pytest.mark.parametrize("n", [1, 2, 999, 1000])
def test_field_median_held_as_counts_is_numpys(n):
    """The median of |MagX, MagY, MagZ| from distinct squared magnitudes and their counts, fed
    in pieces, is numpy's median of every magnitude (int16 fields); float fields as well."""
    rng = np.random.default_rng(n)
    logged = rng.integers(-600, 600, (n, 3)).astype(np.float64)
    for chars in ("hhh", "fff"):
        med = dataflash_chunks._NormMedian()
        for part in np.array_split(logged, 3):
            med.add(part, chars)
        assert med.median() == np.median(np.linalg.norm(logged, axis=1))
    assert len(med.floats) == 3


def test_convert_and_diagnose_read_a_log_piece_by_piece(tmp_path, monkeypatch, capsys):
    """``convert`` writes the whole read's track from the pieces; ``diagnose`` of a log longer
    than the subsample threshold goes through the stratified subsample of the pieces (a minute
    of log keeps every block), every sample counted, also ``--cal log``."""
    import json

    from streamcal.cli import main
    from streamcal.diagnosis import subsample

    path = _selfmade(tmp_path, seconds=60.0)
    monkeypatch.setattr(dataflash_chunks, "PIECE_BYTES", 1 << 14)
    seen = []
    real = dataflash_chunks._survey
    monkeypatch.setattr(dataflash_chunks, "_survey", lambda *a: seen.append(a) or real(*a))
    out = tmp_path / "out.csv"
    assert main(["convert", str(path), "-o", str(out)]) == 0
    whole = dataflash.read_dataflash(path)
    got = Track.read(out)
    assert seen and len(got) == len(whole)
    for name in whole.columns:
        np.testing.assert_allclose(got.columns[name], whole.columns[name], rtol=1e-9,
                                   err_msg=name)
    monkeypatch.setattr(subsample, "LONG_SAMPLES", 1000)
    for extra in ([], ["--cal", "log"]):
        capsys.readouterr()
        assert main(["diagnose", str(path), "--json", *extra]) == 0
        d = json.loads(capsys.readouterr().out)
        assert d["samples_total"] == len(whole.t_mag) >= d["samples_used"] > 0
        assert d["subsample_rule"].startswith("stratified subsample")
        assert d["outlier_spans_over"] == "recording"


def test_reading_in_pieces_holds_less_than_the_whole_read(tmp_path):
    """Peak memory (tracemalloc) while going through a log piece by piece, each Track dropped
    once seen, is a fraction of the whole read's: it does not hold the log."""
    import tracemalloc

    path = _selfmade(tmp_path, seconds=120.0)

    def peak(read):
        tracemalloc.start()
        try:
            read()
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    whole = peak(lambda: dataflash.read_dataflash(path))
    pieces = peak(lambda: [len(c) for c in
                           dataflash_chunks.iter_dataflash_chunks(path, piece_bytes=1 << 16)])
    assert pieces < whole / 3, (pieces, whole)


@pytest.mark.parametrize("firmware, before", [("ArduCopter V3.5.7 (b11c6af3)", True),
                                              ("ArduCopter V3.6.12 (a76b3ef7)", False)])
def test_firmware_order_in_pieces_is_the_whole_track(tmp_path, firmware, before):
    """A log flown with a motor term and a soft-iron matrix, in either order of ArduPilot's
    corrections: undone the same way piece by piece as whole."""
    path = _selfmade(tmp_path, motor_comp=np.array([150.0, -90.0, 210.0]), firmware=firmware,
                     motor_before_matrix=before)
    check_chunks_are_the_whole_track(path)
