"""Text recordings: MotionCal Raw: captures, other CSV/TSV with --columns/--unit, tracks."""
import gzip

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.errors import InputError, TrackError
from streamcal.inputs import detect, read_recording
from streamcal.inputs.track import Track


def test_raw_capture_uses_motioncal_scales(tmp_path):
    path = tmp_path / "capture.log"
    path.write_text("MotionCal sketch v1\nRaw:0,0,8192,16,0,-16,100,-200,300\r\n"
                    "Uni:0.00,0.00,1.00\nRaw:10,20,8000,0,0,0,-5,5,450\n")
    assert detect(path) == "raw"
    track = read_recording(path)
    np.testing.assert_allclose(track.mag, [[10.0, -20.0, 30.0], [-0.5, 0.5, 45.0]])
    np.testing.assert_allclose(track.accel[0], [0, 0, 9.80665])
    np.testing.assert_allclose(track.gyro[0], np.radians([1.0, 0, -1.0]))
    assert track.metadata["other_lines_skipped"] == "2"
    assert "no time stamps" in track.metadata["time"]


def test_raw_capture_bad_line(tmp_path):
    path = tmp_path / "capture.txt"
    path.write_text("Raw:1,2,3,4,5,6,7,8,9\nRaw:1,2,x,4,5,6,7,8,9\n")
    with pytest.raises(InputError, match="malformed"):
        read_recording(path)
    assert len(read_recording(path, skip_bad_rows=True).mag) == 1


@pytest.mark.parametrize("unit,factor", [("uT", 1.0), ("nT", 1e-3), ("mG", 0.1), ("G", 100.0)])
def test_columns_and_units(tmp_path, unit, factor):
    path = tmp_path / "other.tsv"
    path.write_text("# exported by a logger\ntime\tBx\tBy\tBz\tI_motor\n"
                    "0.0\t100\t-200\t300\t1.5\n0.1\t110\t-190\t\t\n0.2\t120\t-180\t280\t2.0\n")
    with pytest.raises(InputError, match="partial mag"):
        read_recording(path, columns="mx=Bx,my=By,mz=Bz,t=time", unit=unit)
    path.write_text("time\tBx\tBy\tBz\tI_motor\n0.0\t100\t-200\t300\t1.5\n0.2\t120\t-180\t280\t\n")
    track = read_recording(path, columns="mx=Bx,my=By,mz=Bz,t=time,motor_current=I_motor",
                           unit=unit)
    np.testing.assert_allclose(track.mag, np.array([[100, -200, 300], [120, -180, 280]]) * factor)
    assert track.mag_unit == "uT" and track.aux_names == ["motor_current"]
    assert np.isnan(track.columns["motor_current"][1])


def test_columns_counts_unit_and_errors(tmp_path, capsys):
    path = tmp_path / "c.csv"
    path.write_text("a,b,c\n1,2,3\n4,5,oops\n")
    assert detect(path) == "csv"
    with pytest.raises(TrackError) as info:
        read_recording(path, columns="mx=a,my=b,mz=c", unit="counts")
    assert info.value.line == 3 and info.value.column == "c"
    track = read_recording(path, columns="mx=a,my=b,mz=c", unit="counts", skip_bad_rows=True)
    assert track.mag_unit == "counts" and track.skipped_rows == 1
    with pytest.raises(InputError, match="header does not have"):
        read_recording(path, columns="mx=a,my=b,mz=zz")
    with pytest.raises(TrackError, match="--columns") as info:
        read_recording(path)
    assert info.value.line == 1 and info.value.column in ("t", "mx")
    out = tmp_path / "t.csv"
    assert main(["convert", str(path), "-o", str(out), "--columns", "mx=a,my=b,mz=c",
                 "--skip-bad-rows"]) == 0
    assert Track.read(out).metadata["input_format"] == "csv-columns"
    assert main(["convert", str(path), "-o", str(out), "--columns", "mx=a"]) == 2
    assert "my, mz" in capsys.readouterr().err


def test_track_files_still_read_plain_and_gzipped(tmp_path):
    t = np.arange(5) * 0.1
    track = Track.from_arrays(t, mag=np.ones((5, 3)), metadata={"sensor": "x"})
    track.write(tmp_path / "a.csv.gz")
    with gzip.open(tmp_path / "a.csv.gz", "rb") as handle:
        assert handle.read(20).startswith(b"# streamcal-track")
    back = read_recording(tmp_path / "a.csv.gz")
    np.testing.assert_array_equal(back.mag, track.mag)
    with pytest.raises(InputError, match="--unit needs --columns"):
        read_recording(tmp_path / "a.csv.gz", unit="mG")
