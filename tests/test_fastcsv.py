"""The pandas fast path of the track parser (streamcal.inputs.fastcsv) returns exactly what
numpy's path returns, and declines whatever the checking path must judge."""
import numpy as np
import pytest

from streamcal.inputs import chunks, fastcsv, trackio
from streamcal.sim import simulate

pytest.importorskip("pandas")


def _text(rows=3000, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(rows, 5)) * 10.0 ** rng.integers(-6, 6, size=(rows, 5))
    v[rng.random(v.shape) < 0.3] = np.nan
    return trackio.format_rows({str(j): v[:, j] for j in range(5)}), v


def test_same_values_as_numpy_loadtxt_bit_for_bit():
    text, v = _text()
    body = text.rstrip("\n")
    fast = fastcsv.parse_plain(body.encode(), len(v), 5, min_bytes=0)
    np.testing.assert_array_equal(fast, v)    # NaN for every empty cell, every float exact
    np.testing.assert_array_equal(fast, trackio._parse_fast(body, len(v), 5))
    np.testing.assert_array_equal(fastcsv.parse_plain(text.encode(), len(v), 5, min_bytes=0), v)


@pytest.mark.parametrize("bad", ["1,2,3,4\n", "1,2,3,4,5,6\n", "1,2,1e,4,5\n", "1,2,.,4,5\n",
                                 "1,2,--1,4,5\n", "1, ,3,4,5\n", "1,2,3,4\n1,2,3,4,5,6\n"])
def test_declines_rows_the_checking_path_must_judge(bad):
    text, v = _text(50)
    lines = text.splitlines(keepends=True)
    data = "".join(lines[:20]) + bad + "".join(lines[20:])
    n = data.count("\n")
    assert fastcsv.parse_plain(data.encode(), n, 5, min_bytes=0) is None


def test_below_the_size_numpy_parses(monkeypatch):
    text, v = _text(10)
    assert fastcsv.parse_plain(text.encode(), len(v), 5) is None


def test_chunked_reading_of_a_large_track_equals_the_whole_file_read(tmp_path):
    track = simulate(400.0, 3, noise_uT=0.4, outlier_bursts=1).track
    path = tmp_path / "t.csv"
    track.write(path)
    whole = trackio.read(path)   # 1 MB slices: numpy's parser
    parts = list(chunks.iter_track_chunks(path, rows=60_000))
    assert len(parts) > 1 and path.stat().st_size / len(parts) > fastcsv.MIN_BYTES
    for name, col in whole.columns.items():
        np.testing.assert_array_equal(np.concatenate([p.columns[name] for p in parts]), col)
    np.testing.assert_array_equal(np.concatenate([p.lines for p in parts]), whole.lines)


def test_an_error_in_a_large_chunk_still_names_line_and_column(tmp_path):
    track = simulate(300.0, 4, noise_uT=0.4).track
    path = tmp_path / "t.csv"
    track.write(path)
    lines = path.read_text().splitlines(keepends=True)
    k = len(lines) // 2
    cells = lines[k].rstrip("\n").split(",")
    cells[1] = "1e"
    lines[k] = ",".join(cells) + "\n"
    path.write_text("".join(lines))
    with pytest.raises(trackio.TrackError) as err:
        list(chunks.iter_track_chunks(path, rows=200_000))
    assert err.value.line == k + 1 and err.value.column == lines[[i for i, l in enumerate(
        lines) if l.startswith("t,")][0]].split(",")[1]
