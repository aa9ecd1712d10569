"""The chunked track reader gives what the whole-file reader gives: the same rows, lines and
skip counts when concatenated, the same TrackError (file, line, column, message) otherwise."""
from __future__ import annotations

import gzip

import numpy as np
import pytest
from hypothesis import given, settings, HealthCheck, strategies as st

from streamcal.errors import TrackError
from streamcal.inputs import chunks
from streamcal.inputs.chunks import iter_track_chunks
from streamcal.inputs.track import Track
from tests._corruption import corrupt
from tests.test_track_fuzz import chaos_ops, render, valid_tracks

FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


def _outcome(read):
    try:
        return read()
    except TrackError as err:
        return ("error", str(err), err.line, err.column)


def _whole(path, skip):
    t = Track.read(path, skip_bad_rows=skip)
    return (t.columns, t.lines, t.skipped_rows, t.skip_reasons)


def _chunked(path, skip, rows):
    parts = list(iter_track_chunks(path, rows=rows, skip_bad_rows=skip))
    assert all(len(p) <= rows for p in parts)
    names = list(parts[0].columns)
    return ({n: np.concatenate([p.columns[n] for p in parts]) for n in names},
            np.concatenate([p.lines for p in parts]), sum(p.skipped_rows for p in parts),
            [r for p in parts for r in p.skip_reasons][:10])


def _assert_same(a, b):
    if a[0] == "error" or b[0] == "error":
        assert a == b
        return
    assert list(a[0]) == list(b[0])
    for name in a[0]:
        np.testing.assert_array_equal(a[0][name], b[0][name])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2:] == b[2:]


@FUZZ
@given(track=valid_tracks(), ops=st.lists(chaos_ops, min_size=0, max_size=3), data=st.data(),
       skip=st.booleans(), rows=st.integers(1, 6), read_bytes=st.sampled_from([7, 64, 1 << 20]))
@pytest.mark.slow
def test_chunks_match_the_whole_file_reader(tmp_path, monkeypatch, track, ops, data, skip, rows,
                                            read_bytes):
    monkeypatch.setattr(chunks, "READ_BYTES", read_bytes)
    meta, names, cells, _ = track
    path = tmp_path / "chunky.csv"
    path.write_bytes(corrupt(render(meta, names, cells), ops, data))
    chunked, whole = _outcome(lambda: _chunked(path, skip, rows)), _outcome(lambda: _whole(path, skip))
    if whole[0] == "error" and "gzip" in whole[1] and chunked != whole:
        # a stream meets the damage only at its end: a bad cell or line before it comes first,
        # else the damage itself (worded by the decompressor where the stream broke)
        assert chunked[0] == "error" and (chunked[2] is not None or "damaged gzip" in chunked[1]), chunked
        return
    _assert_same(chunked, whole)


def test_time_going_backwards_across_a_chunk_boundary_is_located(tmp_path):
    path = tmp_path / "back.csv.gz"
    path.write_bytes(gzip.compress(b"t,mx,my,mz\n0,1,2,3\n2,1,2,3\n1,1,2,3\n3,1,2,3\n"))
    chunked = iter_track_chunks(path, rows=3)
    first = next(chunked)          # lines 1-3: header, t=0, t=2
    assert first.lines.tolist() == [2, 3] and first.t.tolist() == [0, 2]
    with pytest.raises(TrackError) as err:
        next(chunked)              # lines 4-5: t=1 (after t=2 in the previous chunk), t=3
    assert (err.value.line, err.value.column) == (4, "t")
    assert str(err.value).endswith("time goes backwards: t=1.0 after t=2.0")
    kept = list(iter_track_chunks(path, rows=3, skip_bad_rows=True))
    assert np.concatenate([c.t for c in kept]).tolist() == [0, 2, 3]
    assert sum(c.skipped_rows for c in kept) == 1


def test_real_gzip_track_in_chunks_equals_the_whole(real_tracks_dir):
    path = real_tracks_dir / "sunsided_set2_fullsphere.csv.gz"
    _assert_same(_chunked(path, False, 1000), _whole(path, False))


def check_blocks_across_chunks_are_the_whole_tracks_blocks(path) -> None:
    """Blocks of 50 cut from chunks of 37 rows are the whole track's blocks of 50."""
    from streamcal.inputs.chunks import iter_track_blocks

    whole = list(Track.read(path).blocks(50))
    cut = list(iter_track_blocks(iter_track_chunks(path, rows=37), 50))
    assert [len(b.t) for b in cut] == [len(b.t) for b in whole]
    for a, b in zip(cut, whole):
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.mag, b.mag)
        assert a.source == b.source


def check_replay_output_does_not_depend_on_the_chunk_size(path, monkeypatch, capsys) -> str:
    """``replay --json`` reading 50 000 or 23 rows at a time prints the same; returns it."""
    from streamcal.cli import main, replay

    outputs = []
    for rows in (50_000, 23):
        monkeypatch.setattr(replay, "_CHUNK_ROWS", rows)
        assert main(["replay", str(path), "--sync-fits", "--json"]) == 0
        outputs.append(capsys.readouterr().out)
    assert outputs[0] == outputs[1] and '"event": "summary"' in outputs[0]
    return outputs[0]


def test_blocks_across_chunks_are_the_whole_tracks_blocks(real_tracks_dir):
    check_blocks_across_chunks_are_the_whole_tracks_blocks(
        real_tracks_dir / "tiva_mpu9250_mag_03.csv")


def test_replay_output_does_not_depend_on_the_chunk_size(real_tracks_dir, monkeypatch, capsys):
    check_replay_output_does_not_depend_on_the_chunk_size(
        real_tracks_dir / "tiva_mpu9250_mag_03.csv", monkeypatch, capsys)
