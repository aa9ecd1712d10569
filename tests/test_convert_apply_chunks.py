"""convert and apply read section-1 tracks in chunks: output identical to the whole-file path
(real tracks and a simulated one with asynchronous mag / IMU / temp rows), atomic on error."""
import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import apply as apply_cli
from streamcal.cli import convert as convert_cli
from streamcal.cli import main
from streamcal.export.apply import apply_calibration, write_applied
from streamcal.inputs.track import Track
from streamcal.sim import simulate

from .conftest import REAL_TRACKS, real_path

REAL_TRACK = REAL_TRACKS / "broad_02_undisturbed_slow_rotation_B.csv.gz"


@pytest.fixture(params=["temp on IMU rows", "sparse temp", "sparse temp on mag rows"])
def sim_track(tmp_path, request):
    """Mag at 100 Hz, IMU at 37 Hz on other instants, temp on the IMU rows or on every 25th of
    them only, or on every 50th magnetometer row: interpolation across chunk boundaries matters
    (the last one needs rows before the held ones as context)."""
    sim = simulate(duration_s=60.0, seed=5, imu_rate_hz=37.0, motor=False)
    path = tmp_path / "sim.csv"
    columns = dict(sim.track.columns)
    if request.param == "sparse temp":
        temp = np.array(columns["temp"])
        sampled = np.flatnonzero(~np.isnan(temp))
        temp[np.setdiff1d(sampled, sampled[::25])] = np.nan
        columns["temp"] = temp
    if request.param == "sparse temp on mag rows":
        temp = np.array(columns["temp"])
        ok = ~np.isnan(temp)
        mag_rows = np.flatnonzero(~np.isnan(columns["mx"]))[::50]
        sparse = np.full(len(temp), np.nan)
        sparse[mag_rows] = np.interp(columns["t"][mag_rows], columns["t"][ok], temp[ok])
        columns["temp"] = sparse
    Track(columns, sim.track.metadata).write(path)
    return path, sim


def _whole_apply(cal, track_path, cal_path, out):
    """The whole-file apply, as the command did before reading in chunks."""
    track = Track.read(track_path)
    cov = track.covariates_at_mag()
    accel = np.column_stack([cov[c] for c in ("ax", "ay", "az")]) \
        if all(c in cov for c in ("ax", "ay", "az")) else None
    applied = apply_calibration(cal, track.t_mag, track.mag, cov, accel)
    meta = {"streamcal-applied": "1", "calibration": str(cal_path), "recording": str(track_path),
            "field": (f"|B| = {applied.field_scale:.6g} {cal.unit} (the calibration's field)"
                      if applied.field_known else
                      f"|B| unknown: fields scaled by K's mean radius {applied.field_scale:.6g} "
                      f"{cal.unit}"),
            "heading": ("degrees from magnetic north of body x, tilt-compensated with the "
                        "accelerometer" if accel is not None else "none: no accelerometer")}
    write_applied(out, applied, meta)


def check_convert_chunked_equals_whole(path, tmp_path, monkeypatch, suffix: str,
                                       rows: int) -> None:
    """``convert`` reading ``rows`` rows at a time writes the bytes the whole track writes."""
    monkeypatch.setattr(convert_cli, "CHUNK_ROWS", rows)
    out, ref = tmp_path / f"out{suffix}", tmp_path / f"ref{suffix}"
    assert main(["convert", str(path), "-o", str(out)]) == 0
    Track.read(path).write(ref)
    assert out.read_bytes() == ref.read_bytes()


def check_apply_chunked_equals_whole(path, tmp_path, monkeypatch, rows: int) -> None:
    """``apply`` of a plain K, b calibration reading ``rows`` rows at a time writes the bytes the
    whole-file apply writes."""
    monkeypatch.setattr(apply_cli, "CHUNK_ROWS", rows)
    cal_path, out, ref = tmp_path / "cal.json", tmp_path / "out.csv", tmp_path / "ref.csv"
    Calibration(K=np.diag([30.0, 31.0, 29.0]), b=np.array([5.0, -3.0, 1.0]), field=48.0,
                n=1).save(cal_path)
    assert main(["apply", str(cal_path), str(path), "-o", str(out)]) == 0
    _whole_apply(Calibration.load(cal_path), path, cal_path, ref)
    assert out.read_bytes() == ref.read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".csv", ".csv.gz"])
@pytest.mark.parametrize("rows", [997, 100_000])
def test_convert_chunked_equals_whole(tmp_path, monkeypatch, suffix, rows):
    check_convert_chunked_equals_whole(real_path(REAL_TRACK), tmp_path, monkeypatch, suffix,
                                       rows)


@pytest.mark.parametrize("rows", [500, 4096])
def test_apply_chunked_equals_whole_real(tmp_path, monkeypatch, rows):
    check_apply_chunked_equals_whole(real_path(REAL_TRACK), tmp_path, monkeypatch, rows)


@pytest.mark.slow
@pytest.mark.parametrize("rows", [7, 333, 1000])
def test_apply_chunked_equals_whole_async_rows(tmp_path, monkeypatch, sim_track, rows):
    path, sim = sim_track
    monkeypatch.setattr(apply_cli, "CHUNK_ROWS", rows)
    cal_path, out, ref = tmp_path / "cal.json", tmp_path / "out.csv", tmp_path / "ref.csv"
    Calibration(K=sim.truth.K, b=sim.truth.b, n=1,
                model=("hard_iron", "soft_iron", "temperature_offset"),
                effects={"temperature_offset": {"T0": 25.0, "c": [0.05, -0.03, 0.02]}}).save(cal_path)
    assert main(["apply", str(cal_path), str(path), "-o", str(out)]) == 0
    _whole_apply(Calibration.load(cal_path), path, cal_path, ref)
    text = out.read_text()
    assert "heading_deg" in text.split("\n", 10)[-2] or "heading_deg" in text[:2000]
    assert out.read_bytes() == ref.read_bytes()


def test_convert_error_midway_leaves_no_output(tmp_path, monkeypatch, sim_track, capsys):
    path, _ = sim_track
    lines = path.read_text().split("\n")
    lines[3000] = lines[3000].replace(",", ",x", 1)     # a bad cell late in the file
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines))
    monkeypatch.setattr(convert_cli, "CHUNK_ROWS", 500)
    out = tmp_path / "out.csv"
    assert main(["convert", str(bad), "-o", str(out)]) != 0
    assert "bad.csv:3001 column 'ax': not a number" in capsys.readouterr().err
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
