"""Track files (SPEC §1): reading, errors with file/line/column, covariates, blocks, writing."""
from __future__ import annotations

import gzip
import os

import numpy as np
import pytest

from streamcal.samples import SampleBlock
from streamcal.inputs import trackio
from streamcal.errors import InputError, TrackError
from streamcal.inputs.track import Track

SPEC_EXAMPLE = """# streamcal-track: 1
# sensor: mpu9250
# source: i2c bus 1 addr 0x68
t,ax,ay,az,gx,gy,gz,mx,my,mz,temp,motor_current
0.000,0.112,-0.204,9.791,0.0012,-0.0031,0.0004,21.30,-14.85,-38.10,24.1,0.00
0.010,0.109,-0.198,9.802,0.0011,-0.0029,0.0006,,,,24.1,0.00
"""


def write_text(tmp_path, text: str, name: str = "track.csv") -> str:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return str(path)


def read_text(tmp_path, text: str, name: str = "track.csv", **kw) -> Track:
    return Track.read(write_text(tmp_path, text, name), **kw)


def assert_tracks_equal(a: Track, b: Track) -> None:
    assert list(a.columns) == list(b.columns)
    for name in a.columns:
        np.testing.assert_array_equal(a.columns[name], b.columns[name], err_msg=name)
    assert a.metadata == b.metadata


# ----------------------------------------------------------------------------- reading


def test_spec_example_columns_metadata_units(tmp_path):
    track = read_text(tmp_path, SPEC_EXAMPLE)
    assert len(track) == 2
    assert list(track.metadata) == ["streamcal-track", "sensor", "source"]
    assert track.metadata["source"] == "i2c bus 1 addr 0x68"
    assert track.mag_unit == "uT" and track.accel_unit == "m/s^2"
    np.testing.assert_array_equal(track.t, [0.0, 0.01])
    np.testing.assert_array_equal(track.mag_rows, [True, False])
    np.testing.assert_array_equal(track.mag, [[21.30, -14.85, -38.10]])
    np.testing.assert_array_equal(track.t_mag, [0.0])
    assert track.accel.shape == (2, 3) and track.gyro.shape == (2, 3)
    np.testing.assert_array_equal(track.accel[:, 2], [9.791, 9.802])
    assert track.aux_names == ["motor_current"]
    assert np.isnan(track.columns["mx"][1])
    assert track.has("temp") and track.has("motor_current") and track.has("mag")
    assert not track.has("pressure")
    assert track.columns["t"].dtype == np.float64
    assert list(track.lines) == [5, 6]


def test_columns_in_any_order_and_declared_units(tmp_path):
    track = read_text(tmp_path, "# mag_unit: counts (nominal 0.15 uT/LSB)\n"
                                "# accel_unit: g\nmz,az,t,my,ay,duty,mx,ax\n"
                                "3,0.9,0,2,0.1,0.5,1,0\n")
    np.testing.assert_array_equal(track.mag, [[1, 2, 3]])
    np.testing.assert_array_equal(track.accel, [[0, 0.1, 0.9]])
    assert track.mag_unit == "counts" and track.accel_unit == "g"
    assert track.aux_names == ["duty"]
    assert not track.has("gyro") and track.gyro.shape == (0, 3)


@pytest.mark.parametrize("declared, unit", [("µT", "uT"), ("uT (gauss x 100)", "uT"),
                                             ("counts", "counts"), ("mG; raw", "mG")])
def test_mag_unit_spellings(tmp_path, declared, unit):
    track = read_text(tmp_path, f"# mag_unit: {declared}\nt,mx,my,mz\n0,1,2,3\n")
    assert track.mag_unit == unit


def test_unknown_metadata_kept_in_order_and_comment_lines_ignored(tmp_path):
    track = read_text(tmp_path, "# zeta: 1\n# a comment without a colon\n\n# alpha: x: y\n"
                                "t,mx,my,mz\n0,1,2,3\n")
    assert list(track.metadata.items()) == [("zeta", "1"), ("alpha", "x: y")]


def test_async_rows_imu_only_mag_only(tmp_path):
    track = read_text(tmp_path, "t,ax,ay,az,mx,my,mz,temp\n"
                                "0.0,0,0,9.8,,,,20\n"
                                "0.1,,,,1,2,3,\n"
                                "0.2,0,0,9.7,,,,21\n"
                                "0.3,0,0,9.6,4,5,6,22\n")
    np.testing.assert_array_equal(track.mag_rows, [False, True, False, True])
    np.testing.assert_array_equal(track.accel_rows, [True, False, True, True])
    np.testing.assert_array_equal(track.t_mag, [0.1, 0.3])
    np.testing.assert_array_equal(track.mag, [[1, 2, 3], [4, 5, 6]])
    assert track.accel.shape == (3, 3)


def test_crlf_bom_blank_and_comment_lines_keep_physical_line_numbers(tmp_path):
    text = "\ufeff# a: b\r\n\r\nt,mx,my,mz\r\n0,1,2,3\r\n\r\n# note\r\n1,x,2,3\r\n"
    with pytest.raises(TrackError) as err:
        read_text(tmp_path, text)
    assert (err.value.line, err.value.column) == (7, "mx")
    track = read_text(tmp_path, text.replace("1,x", "1,4"))
    assert track.metadata == {"a": "b"}
    assert list(track.lines) == [4, 7]


def test_gzip_recognised_by_magic_bytes_not_extension(tmp_path):
    zipped = tmp_path / "plain_name.csv"
    zipped.write_bytes(gzip.compress(SPEC_EXAMPLE.encode()))
    plain = write_text(tmp_path, SPEC_EXAMPLE, "looks_zipped.csv.gz")
    assert_tracks_equal(Track.read(zipped), Track.read(plain))


def test_huge_finite_values_load(tmp_path):
    track = read_text(tmp_path, "t,mx,my,mz\n0,1e308,-1.7976931348623157e308,5e-324\n")
    np.testing.assert_array_equal(track.mag, [[1e308, -1.7976931348623157e308, 5e-324]])


def test_fast_and_slow_parsers_agree_on_clean_cells():
    rng = np.random.default_rng(7)
    values = rng.normal(size=(200, 5)) * 10.0 ** rng.integers(-300, 300, size=(200, 5))
    values[rng.random(values.shape) < 0.3] = np.nan
    styles = [repr, lambda v: f"{v:.3e}", lambda v: f" {v:+.6f} ", lambda v: f"{v:E}"]
    lines = [",".join("" if np.isnan(v) else styles[(i + j) % 4](float(v))
                      for j, v in enumerate(row)) for i, row in enumerate(values)]
    fast = trackio._parse_fast("\n".join(lines), len(lines), 5)
    slow, problems = trackio._parse_slow(lines, ["t", "mx", "my", "mz", "a"])
    assert fast is not None and not problems
    np.testing.assert_array_equal(fast, slow)
    assert np.array_equal(np.isnan(fast), np.isnan(values))


# ----------------------------------------------------------------------------- errors

HEADER = "# streamcal-track: 1\n# sensor: x\nt,mx,my,mz,temp\n"  # data starts on line 4

ROW_ERRORS = [
    ("0,1,2,3,20\n1,abc,2,3,20\n", 5, "mx", "not a number"),
    ("0,1,2,3,20\n1,1,2,3,nan\n", 5, "temp", "non-finite"),
    ("0,1,2,3,20\n1,1,2,-inf,20\n", 5, "mz", "non-finite"),
    ("0,1,2,3,20\n1,1,1e999,3,20\n", 5, "my", "overflows"),
    ("0,1,2,3,20\n1,1,2,3\n", 5, "temp", "expected 5 cells"),
    ("0,1,2,3,20\n1,1,2,3,20,9\n", 5, None, "found 6"),
    ("0,1,2,3,20\n2,1,2,3,20\n1.5,1,2,3,20\n", 6, "t", "time goes backwards"),
    ("0,1,2,3,20\n1,1,,3,20\n", 5, "my", "partial mag"),
    ("0,1,2,3,20\n,1,2,3,20\n", 5, "t", "every row needs t"),
    ("0,1,2,3,20\n1,1_0,2,3,20\n", 5, "mx", "not a number"),
    ('0,1,2,3,20\n1,"1",2,3,20\n', 5, "mx", "not a number"),
    ("0,1,2,3,20\n1,0x10,2,3,20\n", 5, "mx", "not a number"),
    ("0,1,2,3,20\n1,1.2.3,2,3,20\n", 5, "mx", "not a number"),
    ("0,1,2,3,20\n1,\x00,2,3,20\n", 5, "mx", "not a number"),  # numpy str would drop it
    ("0,1,2,3,20\n1,1,2\x00,3,20\n", 5, "my", "not a number"),
    ("0,1,2,3,20\n1,1,2,3,\u0662\n", 5, "temp", "not a number"),  # non-ASCII digit
]


@pytest.mark.parametrize("body, line, column, words", ROW_ERRORS)
def test_row_errors_name_file_line_column(tmp_path, body, line, column, words):
    with pytest.raises(TrackError) as err:
        read_text(tmp_path, HEADER + body)
    assert (err.value.line, err.value.column) == (line, column)
    assert words in str(err.value) and "track.csv" in str(err.value)


@pytest.mark.parametrize("body, line, column, words", ROW_ERRORS)
def test_skip_bad_rows_skips_and_counts(tmp_path, body, line, column, words):
    track = read_text(tmp_path, HEADER + body, skip_bad_rows=True)
    assert track.skipped_rows == 1 and len(track.skip_reasons) == 1
    assert track.skip_reasons[0].startswith(f"line {line}") and words in track.skip_reasons[0]
    assert line not in list(track.lines)
    assert np.all(np.diff(track.t) >= 0)


def test_first_error_is_the_earliest_line(tmp_path):
    with pytest.raises(TrackError) as err:
        read_text(tmp_path, HEADER + "0,1,2,3,20\n5,1,2,3,20\n4,1,2,3,20\n6,x,2,3,20\n")
    assert (err.value.line, err.value.column) == (6, "t")


def test_skip_bad_rows_counts_all_and_keeps_first_reasons(tmp_path):
    body = "".join(f"{i},1,2,3,{'x' if i % 2 else '20'}\n" for i in range(40))
    track = read_text(tmp_path, HEADER + body, skip_bad_rows=True)
    assert len(track) == 20 and track.skipped_rows == 20
    assert len(track.skip_reasons) == trackio.MAX_REASONS
    assert track.skip_reasons[0] == "line 5 column 'temp': not a number: 'x'"


def test_skip_bad_rows_time_is_non_decreasing_over_kept_rows(tmp_path):
    track = read_text(tmp_path, HEADER + "".join(f"{t},1,2,3,20\n" for t in [0, 1, 3, 2, 2.5, 4]),
                      skip_bad_rows=True)
    np.testing.assert_array_equal(track.t, [0, 1, 3, 4])
    assert track.skipped_rows == 2


def test_skip_bad_rows_all_bad_is_an_error(tmp_path):
    with pytest.raises(TrackError, match="no valid data rows"):
        read_text(tmp_path, HEADER + "0,x,2,3,20\n", skip_bad_rows=True)


STRUCTURAL = [
    ("", None, None, "empty file"),
    ("\n  \n", None, None, "empty file"),
    ("# a: b\n# c: d\n", None, None, "no header"),
    ("# a: b\nt,mx,my,mz\n", 2, None, "no data rows"),
    ("t,mx,my\n0,1,2\n", 1, "mz", "missing required"),
    ("mx,my,mz\n1,2,3\n", 1, "t", "missing required"),
    ("t,mx,my,mz,ax,ay\n0,1,2,3,4,5\n", 1, "az", "threes"),
    ("t,mx,my,mz,mx\n0,1,2,3,4\n", 1, "mx", "duplicate"),
    ("t,mx,my,mz,\n0,1,2,3,4\n", 1, None, "empty column name"),
    ("t,mx,my,mz,motor current\n0,1,2,3,4\n", 1, "motor current", "invalid column name"),
    ("0,1,2,3\n1,2,3,4\n", 1, "0", "header"),
    ("# streamcal-track: 2\nt,mx,my,mz\n0,1,2,3\n", None, None, "version"),
]


@pytest.mark.parametrize("skip", [False, True])
@pytest.mark.parametrize("text, line, column, words", STRUCTURAL)
def test_structural_errors_even_when_skipping(tmp_path, text, line, column, words, skip):
    with pytest.raises(TrackError) as err:
        read_text(tmp_path, text, skip_bad_rows=skip)
    assert (err.value.line, err.value.column) == (line, column)
    assert words in str(err.value) and "track.csv" in str(err.value)


def test_non_utf8_byte_named_by_line_and_byte(tmp_path):
    path = tmp_path / "latin1.csv"
    path.write_bytes(b"# a: b\nt,mx,my,mz\n0,1,2,3\n1,2,3\xb5,4\n")
    with pytest.raises(TrackError) as err:
        Track.read(path)
    assert (err.value.line, err.value.column) == (4, "my")
    assert "byte 0xb5 at byte 6" in str(err.value)
    assert Track.read(path, skip_bad_rows=True).skipped_rows == 1
    path.write_bytes(b"# unit: \xb5T\nt,mx,my,mz\n0,1,2,3\n")
    with pytest.raises(TrackError, match="latin1.csv:1: not UTF-8: byte 0xb5"):
        Track.read(path, skip_bad_rows=True)


@pytest.mark.parametrize("damage", ["truncated", "garbage", "trailing"])
def test_damaged_gzip(tmp_path, damage):
    good = gzip.compress((SPEC_EXAMPLE * 1).encode())
    data = {"truncated": good[:-12], "garbage": b"\x1f\x8b" + bytes(range(40)),
            "trailing": good + b"junk"}[damage]
    path = tmp_path / "t.csv.gz"
    path.write_bytes(data)
    with pytest.raises(TrackError, match="t.csv.gz.*gzip"):
        Track.read(path, skip_bad_rows=True)


def test_unreadable_paths(tmp_path):
    with pytest.raises(TrackError, match="missing.csv: cannot read"):
        Track.read(tmp_path / "missing.csv")
    with pytest.raises(TrackError, match="cannot read"):
        Track.read(tmp_path)


# ----------------------------------------------------------------------------- covariates


def test_covariates_same_row_interpolated_and_held(tmp_path):
    # temp sampled at t=1,3 on IMU rows; mag at t=0 (before), 2 (between), 3 (same row), 4 (after)
    track = Track.from_arrays(
        t=[0, 1, 2, 3, 4],
        mag=[[1, 1, 1], [np.nan] * 3, [2, 2, 2], [3, 3, 3], [4, 4, 4]],
        accel=[[np.nan] * 3, [0, 0, 10], [np.nan] * 3, [0, 0, 20], [np.nan] * 3],
        temp=[np.nan, 10, np.nan, 30, np.nan],
        aux={"current": [np.nan] * 5, "duty": [0.5, 0.7, 0.9, np.nan, np.nan]})
    cov = track.covariates_at_mag()
    np.testing.assert_array_equal(cov["t"], [0, 2, 3, 4])
    np.testing.assert_allclose(cov["temp"], [10, 20, 30, 30])
    np.testing.assert_allclose(cov["az"], [10, 15, 20, 20])
    np.testing.assert_allclose(cov["duty"], [0.5, 0.9, 0.9, 0.9])
    assert "current" not in cov and "mx" not in cov
    assert all(v.shape == (4,) for v in cov.values())


def test_covariates_linear_signal_is_reproduced_on_async_grid():
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 10, 500))
    is_mag = rng.random(500) < 0.4
    imu = ~is_mag | (rng.random(500) < 0.2)
    imu[[0, -1]] = True  # mag instants inside the IMU span: no holding at the ends
    temp = np.where(imu, 20 + 0.5 * t, np.nan)
    mag = np.where(is_mag[:, None], rng.normal(size=(500, 3)), np.nan)
    track = Track.from_arrays(t, mag=mag, temp=temp)
    np.testing.assert_allclose(track.covariates_at_mag()["temp"], 20 + 0.5 * t[is_mag],
                               rtol=1e-12)


# ----------------------------------------------------------------------------- arrays, blocks


def test_from_arrays_validates():
    with pytest.raises(TrackError, match="backwards"):
        Track.from_arrays([0, 2, 1], mag=np.zeros((3, 3)))
    with pytest.raises(TrackError, match="partial mag") as err:
        Track.from_arrays([0, 1], mag=[[1, 2, 3], [1, np.nan, 3]])
    assert err.value.column == "my"
    with pytest.raises(TrackError, match="shape"):
        Track.from_arrays([0, 1], mag=np.zeros((2, 2)))
    with pytest.raises(TrackError, match="infinite"):
        Track.from_arrays([0, 1], mag=np.zeros((2, 3)), temp=[1, np.inf])
    with pytest.raises(TrackError, match="finite time"):
        Track.from_arrays([0, np.nan], mag=np.zeros((2, 3)))
    with pytest.raises(TrackError, match="auxiliary"):
        Track.from_arrays([0], mag=np.zeros((1, 3)), aux={"temp": [1]})
    with pytest.raises(TrackError, match="metadata key"):
        Track.from_arrays([0], mag=np.zeros((1, 3)), metadata={"a:b": "c"})


def test_from_arrays_copies_and_is_read_only():
    mag = np.ones((2, 3))
    track = Track.from_arrays([0, 1], mag=mag)
    mag[0, 0] = 5
    assert track.mag[0, 0] == 1
    with pytest.raises(ValueError):
        track.columns["mx"][0] = 3
    assert Track.from_arrays([0], accel=[[0, 0, 9.8]]).mag.shape == (0, 3)


def sample_track(n=23, seed=0) -> Track:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0, 0.01, n))
    mag = rng.normal(size=(n, 3)) * 40
    mag[rng.random(n) < 0.5] = np.nan
    gyro = rng.normal(size=(n, 3))
    return Track.from_arrays(t, mag=mag, accel=rng.normal(size=(n, 3)), gyro=gyro,
                             temp=rng.normal(25, 1, n), aux={"current": rng.random(n)},
                             metadata={"sensor": "mpu9250", "source": "test"})


def test_blocks_and_from_blocks_invert_each_other():
    track = sample_track()
    blocks = list(track.blocks(5))
    assert [len(b) for b in blocks] == [5, 5, 5, 5, 3]
    assert all(isinstance(b, SampleBlock) and b.source == "test" for b in blocks)
    np.testing.assert_array_equal(np.concatenate([b.mag_valid for b in blocks]), track.mag_rows)
    back = Track.from_blocks(blocks, metadata=track.metadata)
    assert_tracks_equal(track, back)
    assert Track.from_blocks(blocks).metadata == {"source": "test"}


def test_blocks_of_mag_only_track_have_no_imu():
    block = next(Track.from_arrays([0, 1], mag=np.ones((2, 3))).blocks(10))
    assert block.accel is None and block.gyro is None and block.temp is None
    assert block.aux == {} and block.mag.shape == (2, 3)
    with pytest.raises(InputError):
        next(Track.from_arrays([0], mag=np.ones((1, 3))).blocks(0))
    with pytest.raises(InputError):
        Track.from_blocks([])


def test_from_blocks_fills_missing_sensors_with_nan():
    a = SampleBlock(t=np.array([0.0, 1.0]), mag=np.ones((2, 3)))
    b = SampleBlock(t=np.array([2.0]), mag=np.full((1, 3), np.nan), accel=np.ones((1, 3)),
                    aux={"duty": np.array([0.3])})
    track = Track.from_blocks([a, b])
    np.testing.assert_array_equal(track.accel_rows, [False, False, True])
    np.testing.assert_array_equal(track.columns["duty"], [np.nan, np.nan, 0.3])
    np.testing.assert_array_equal(track.mag_rows, [True, True, False])


def test_select_mask_slice_indices():
    track = sample_track()
    mask = track.t > np.median(track.t)
    sub = track.select(mask)
    assert len(sub) == mask.sum() and sub.metadata == track.metadata
    np.testing.assert_array_equal(sub.mag, track.mag[mask[track.mag_rows]])
    np.testing.assert_array_equal(track.select(slice(2, 7)).t, track.t[2:7])
    np.testing.assert_array_equal(track.select([1, 4]).columns["current"],
                                  track.columns["current"][[1, 4]])
    with pytest.raises(InputError):
        track.select(mask[:-1])
    with pytest.raises(InputError):
        track.select([4, 1])


# ----------------------------------------------------------------------------- writing


@pytest.mark.parametrize("name", ["out.csv", "out.csv.gz"])
def test_write_read_round_trip_is_exact(tmp_path, name):
    track = sample_track(200, seed=1)
    tiny = Track.from_arrays([0, 0, 1e-300], mag=[[5e-324, -0.0, 1e308], [0.1, 0.2, 0.3],
                                                  [1 / 3, 2 / 3, np.nextafter(1, 2)]])
    for original in (track, tiny):
        original.write(tmp_path / name)
        back = Track.read(tmp_path / name)
        assert list(back.metadata)[0] == "streamcal-track"
        assert_tracks_equal(back, Track.read(tmp_path / name))
        for column in original.columns:
            np.testing.assert_array_equal(back.columns[column], original.columns[column])
        assert {k: v for k, v in back.metadata.items() if k != "streamcal-track"} == \
            original.metadata
    assert (tmp_path / name).read_bytes()[:2] == (b"\x1f\x8b" if name.endswith(".gz") else b"# ")
    assert os.listdir(tmp_path) == [name]  # no temporary file left behind


def test_written_text_format(tmp_path):
    Track.from_arrays([0.0, 0.5], mag=[[1.5, 2, 3], [np.nan] * 3], temp=[20, 21],
                      metadata={"sensor": "x"}).write(tmp_path / "o.csv")
    assert (tmp_path / "o.csv").read_text() == (
        "# streamcal-track: 1\n# sensor: x\nt,mx,my,mz,temp\n"
        "0.0,1.5,2.0,3.0,20.0\n0.5,,,,21.0\n")


def test_read_write_read_of_spec_example(tmp_path):
    first = read_text(tmp_path, SPEC_EXAMPLE)
    first.write(tmp_path / "again.csv.gz")
    assert_tracks_equal(first, Track.read(tmp_path / "again.csv.gz"))


# ----------------------------------------------------------------------------- real tracks


def test_every_real_track_loads(real_tracks_dir):
    files = sorted(p for p in real_tracks_dir.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    assert len(files) >= 20
    for path in files:
        track = Track.read(path)
        assert len(track) > 0 and len(track.mag) > 0, path.name
        assert np.all(np.diff(track.t) >= 0), path.name
        assert np.all(np.isfinite(track.mag)), path.name
        declared = track.metadata.get("mag_unit")
        assert declared is not None, path.name       # "probably uT" → unknown, said as such
        assert declared.startswith(track.mag_unit) or track.mag_unit == "unknown", path.name
        assert track.skipped_rows == 0


def test_real_async_and_gzip_tracks(real_tracks_dir):
    track = Track.read(real_tracks_dir / "sunsided_set1_tiltsphere.csv.gz")
    assert track.mag_unit == "uT"
    assert 0 < track.mag_rows.sum() < len(track)
    assert not np.any(track.mag_rows & track.accel_rows)  # separate mag and IMU rows
    cov = track.covariates_at_mag()
    assert set(cov) == {"t", "ax", "ay", "az", "gx", "gy", "gz", "temp"}
    assert all(np.all(np.isfinite(v)) and v.shape == (len(track.mag),) for v in cov.values())
    tiva = Track.read(real_tracks_dir / "tiva_mpu9250_mag_01.csv.gz")
    assert tiva.mag_unit == "counts" and not tiva.has("accel")
    assert np.all(tiva.mag == np.round(tiva.mag))  # integer counts


def test_real_track_round_trip(tmp_path, real_tracks_dir):
    track = Track.read(real_tracks_dir / "sunsided_set1_tiltsphere.csv.gz")
    track.write(tmp_path / "copy.csv.gz")
    assert_tracks_equal(track, Track.read(tmp_path / "copy.csv.gz"))
