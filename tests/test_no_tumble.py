"""Calibration without a tumble (fit --heading, fit --planar) on simulated vehicles with a known
truth; the plain fit's refusal of a planar track points at them."""
import json
import subprocess
import sys

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.fitting.no_tumble import fit_heading, fit_planar
from streamcal.geomag import parse_date, wmm_field
from streamcal.sim.flight import DATE, LAT, LON, simulated_log

B_TRUE = np.array([12.0, -7.0, 20.0])
#: horizontal soft iron only: what turning in the plane can see
S_PLANAR = np.array([[1.05, 0.03, 0.0], [0.03, 0.97, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def ref():
    return wmm_field(LAT, LON, 0.4, parse_date(DATE))


@pytest.mark.parametrize("seed", [0, 1])
def test_planar_recovers_offsets_and_horizontal_iron(ref, seed):
    track, truth = simulated_log("rover", S=S_PLANAR, b_body=B_TRUE, seed=seed)
    cal = fit_planar(track, ref)
    # 1200 samples at 0.3 µT per axis: σ(b) ~ 0.02 µT; the ±2° tilts leave ~0.1 µT of coupling
    assert np.abs(cal.b - B_TRUE).max() < 0.15
    # the calibrated body field matches the truth's: |S⁻¹ (m − b)| = |e| = the model's field
    field = cal.apply_field(track.mag)
    assert np.median(np.linalg.norm(field, axis=1)) == pytest.approx(ref["intensity_uT"], rel=3e-3)
    und = cal.extra["undetermined"]
    assert {"A33", "A13", "A23", "heading offset", "orientation"} <= set(und)
    assert cal.n_outliers <= 0.01 * cal.n
    # residual of the levelled field: radial and vertical, 0.3 µT each → √2·0.3 = 0.42 µT
    assert cal.rms < 0.55
    again = Calibration.from_json(cal.to_json())
    assert again.extra["undetermined"] == und and again == cal


@pytest.mark.parametrize("heading", [0.0, 30.0, 200.0])
def test_known_heading_recovers_offsets(ref, heading):
    track, _ = simulated_log("still", duration_s=10, heading_deg=heading, b_body=B_TRUE, seed=2)
    cal = fit_heading(track, heading, ref)
    # 100 samples, 0.3 µT noise and 0.05 m/s² accelerometer noise (0.3 mrad of tilt, ~0.02 µT)
    assert np.abs(cal.b - B_TRUE).max() < 0.15
    assert set(cal.extra["undetermined"]) == {"K", "orientation", "heading"}
    # a heading wrong by 5° moves the horizontal offsets by about 2 H sin(2.5°) ≈ 1.8 µT
    wrong = fit_heading(track, heading + 5.0, ref)
    assert np.linalg.norm(wrong.b[:2] - B_TRUE[:2]) > 1.0


def test_known_heading_holds_a_given_iron(ref):
    S = np.array([[1.1, 0.0, 0.0], [0.0, 0.95, 0.02], [0.0, 0.02, 1.0]])
    track, _ = simulated_log("still", duration_s=10, heading_deg=45, S=S, b_body=B_TRUE, seed=4)
    plain = fit_heading(track, 45.0, ref)
    initial = Calibration(K=ref["intensity_uT"] * S, b=np.zeros(3), field=ref["intensity_uT"])
    held = fit_heading(track, 45.0, ref, initial)
    assert np.abs(held.b - B_TRUE).max() < 0.15 < np.abs(plain.b - B_TRUE).max()
    assert "--initial" in held.extra["undetermined"]["K"]


def _fit(*argv):
    return subprocess.run([sys.executable, "-m", "streamcal", "fit", *map(str, argv)],
                          capture_output=True, text=True, timeout=600)


def test_cli_planar_heading_and_the_refusal(tmp_path):
    track, _ = simulated_log("rover", S=S_PLANAR, b_body=B_TRUE, seed=0)
    path = tmp_path / "rover.csv"
    track.write(path)
    plain = _fit(path)
    assert plain.returncode == 1 and "--planar" in plain.stderr and "--heading" in plain.stderr
    run = _fit(path, "--planar", "--json")
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["method"] == "planar" and "A33" in out["undetermined"]
    assert np.abs(np.array(out["b"]) - B_TRUE).max() < 0.15
    still, _ = simulated_log("still", duration_s=10, heading_deg=30, b_body=B_TRUE)
    meta = {k: v for k, v in still.metadata.items() if not k.startswith("gps_")}
    path = tmp_path / "still.csv"
    type(still)(still.columns, meta).write(path)
    nogps = _fit(path, "--heading", 30)
    assert nogps.returncode == 2 and "--lat" in nogps.stderr
    run = _fit(path, "--heading", 30, "--lat", LAT, "--lon", LON, "--date", DATE, "-o",
               tmp_path / "c.json")
    assert run.returncode == 0, run.stderr
    assert "not determined  K" in run.stdout
    cal = Calibration.load(tmp_path / "c.json")
    assert np.abs(cal.b - B_TRUE).max() < 0.15


def test_known_heading_uses_only_the_still_samples(ref):
    from streamcal.inputs.track import Track

    track, _ = simulated_log("still", duration_s=10, heading_deg=30, b_body=B_TRUE, seed=2)
    n = len(track)
    gyro = np.zeros((n, 3))
    gyro[: n // 2, 2] = 0.5          # the first half turning: the heading is not known there
    mag = np.array(track.mag)
    mag[: n // 2] += 40.0            # and its readings are useless
    cols = {k: v for k, v in track.columns.items() if k not in ("mx", "my", "mz")}
    moved = Track.from_arrays(track.t, mag=mag, accel=np.column_stack(
        [cols.pop(c) for c in ("ax", "ay", "az")]), gyro=gyro,
        aux={k: v for k, v in cols.items() if k != "t"}, metadata=track.metadata)
    cal = fit_heading(moved, 30.0, ref)
    assert cal.n == n - n // 2 and np.abs(cal.b - B_TRUE).max() < 0.2


@pytest.mark.parametrize("turns", [0.5, 0.2])
def test_planar_part_of_a_circle(ref, turns):
    """Half a turn (plus the ±20° wander) still locates the centre: the radius is known; a
    fifth of a turn is refused, not answered with offsets several µT off."""
    track, _ = simulated_log("rover", S=S_PLANAR, b_body=B_TRUE, seed=1, turns=turns)
    if turns >= 0.5:
        cal = fit_planar(track, ref)
        assert np.abs(cal.b - B_TRUE).max() < 0.15
        assert cal.extra["planar"]["heading_arc_deg"] >= 180
    else:
        from streamcal.errors import InsufficientDataError

        with pytest.raises(InsufficientDataError, match="half a circle"):
            fit_planar(track, ref)


def test_known_heading_refuses_samples_at_many_headings(ref):
    """A flight turns through every heading: its still moments are not at the heading given,
    and offsets from them would fit none (refused, saying what to do instead)."""
    from streamcal.errors import InsufficientDataError

    track, _ = simulated_log("flight", duration_s=120, b_body=B_TRUE, seed=3)
    with pytest.raises(InsufficientDataError, match="not at one heading.*--planar.*--attitude"):
        fit_heading(track, 90.0, ref)

