"""Track files on simulated recordings: what tests/test_track.py, tests/test_track_chunks.py and
tests/test_convert_apply_chunks.py check on the real tracks — asynchronous mag / IMU rows in a
gzip file, raw counts, an exact round trip, the chunked reader equal to the whole-file one, and
convert / apply / replay output independent of the chunk size."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.inputs.track import Track
from streamcal.sim import simulate

from .test_convert_apply_chunks import (check_apply_chunked_equals_whole,
                                        check_convert_chunked_equals_whole)
from .test_sim_counts_log import counts_log
from .test_track import assert_tracks_equal
from .test_track_chunks import (_assert_same, _chunked, _whole,
                                check_blocks_across_chunks_are_the_whole_tracks_blocks,
                                check_replay_output_does_not_depend_on_the_chunk_size)


@pytest.fixture(scope="module")
def gz_track(tmp_path_factory):
    """A 40 s simulated tumble: 100 Hz mag and 200 Hz IMU rows, temperature, gzip."""
    path = tmp_path_factory.mktemp("tracks") / "sim.csv.gz"
    simulate(40.0, 21, motor=False).track.write(path)
    return path


@pytest.fixture(scope="module")
def counts(tmp_path_factory):
    return counts_log(tmp_path_factory.mktemp("counts") / "counts.csv", 22, duration_s=30.0)


def test_async_gzip_track_and_its_covariates(gz_track):
    track = Track.read(gz_track)
    assert gz_track.read_bytes()[:2] == b"\x1f\x8b"
    assert track.mag_unit == "uT" and track.skipped_rows == 0
    assert 0 < track.mag_rows.sum() < len(track)
    assert not np.any(track.mag_rows & track.accel_rows)
    cov = track.covariates_at_mag()
    assert set(cov) == {"t", "ax", "ay", "az", "gx", "gy", "gz", "temp"}
    assert all(np.all(np.isfinite(v)) and v.shape == (len(track.mag),) for v in cov.values())


def test_counts_track_is_read_as_counts(counts):
    track = Track.read(counts)
    assert track.mag_unit == "counts" and not track.has("accel")
    assert np.all(track.mag == np.round(track.mag)) and np.all(np.diff(track.t) >= 0)
    assert track.metadata["mag_unit"].startswith(track.mag_unit)


def test_gzip_round_trip_is_exact(gz_track, tmp_path):
    track = Track.read(gz_track)
    track.write(tmp_path / "copy.csv.gz")
    assert_tracks_equal(track, Track.read(tmp_path / "copy.csv.gz"))


def test_gzip_track_in_chunks_equals_the_whole(gz_track):
    _assert_same(_chunked(gz_track, False, 1000), _whole(gz_track, False))


def test_blocks_across_chunks_are_the_whole_tracks_blocks(counts):
    check_blocks_across_chunks_are_the_whole_tracks_blocks(counts)


def test_replay_output_does_not_depend_on_the_chunk_size(counts, monkeypatch, capsys):
    out = check_replay_output_does_not_depend_on_the_chunk_size(counts, monkeypatch, capsys)
    assert '"event": "accepted"' in out      # the replay did calibrate


@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
@pytest.mark.parametrize("rows", [997, 100_000])
def test_convert_chunked_equals_whole(gz_track, tmp_path, monkeypatch, suffix, rows):
    check_convert_chunked_equals_whole(gz_track, tmp_path, monkeypatch, suffix, rows)


@pytest.mark.parametrize("rows", [500, 4096])
def test_apply_chunked_equals_whole(gz_track, tmp_path, monkeypatch, rows):
    check_apply_chunked_equals_whole(gz_track, tmp_path, monkeypatch, rows)
