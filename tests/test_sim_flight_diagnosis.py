"""Diagnosing a flight slice against the autopilot's own calibration (``--cal autopilot``), on
self-made ArduPilot logs (tests/_selfmade_logs.py): what tests/test_flight_hidden_effect.py,
tests/test_held_recheck.py and tests/test_report_flight.py check on the real flights — a motor
field hidden in the log is found as aux_interference on its channel, a clean log does not invent
one, the re-estimated parameters are determined and plausible, the CLI and the report show it."""
from __future__ import annotations

import json

import pytest

import streamcal
from streamcal.cli import main
from streamcal.diagnosis.held.fit import field_radius
from streamcal.diagnosis.held.recheck import SUSPICIOUS_SIGMAS, plausible_range
from streamcal.fitting.damped_lm import STATUSES
from streamcal.inputs import autopilot_calibration, read_recording
from streamcal.inputs.track import Track

from ._selfmade_logs import flight_slice, write_dataflash

MOTOR_UT = 3.0   # at the channel's full range, as the real-log tests inject


def _log(tmp_path_factory, name, duration_s=60.0, **kw):
    path = write_dataflash(tmp_path_factory.mktemp("flight") / name,
                           flight_slice(duration_s, seed=5, **kw))
    track = read_recording(path)
    return path, track, autopilot_calibration(track)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return _log(tmp_path_factory, "clean.bin")


@pytest.fixture(scope="module", params=["throttle", "rcou_c3"])
def motor(request, tmp_path_factory):
    return request.param, _log(tmp_path_factory, f"motor_{request.param}.bin",
                               motor_uT=MOTOR_UT, motor_channel=request.param)


def test_hidden_motor_field_is_aux_interference_on_its_channel(motor):
    channel, (_, track, cal) = motor
    d = streamcal.diagnose(track, calibration=cal)
    top = d.to_dict()["candidates"][0]
    assert top["effect"] == "aux_interference"
    assert top["significant"] and top["material"]
    assert top["rms_after"] < 0.75 * top["rms_before"]
    assert next(iter(d.held.aux_channels)) == channel   # the channel the residual follows most
    added = [s.get("added") for s in d.to_dict()["ladder"]]
    assert "aux_interference" in added
    # what the plausibility rule marks (a slice does not determine them) is never added
    marked = {c.effect for c in d.candidates if getattr(c, "implausible", "")}
    assert "aux_interference" not in marked and not marked & set(added)
    assert d.to_dict()["calibration_source"].endswith("COMPASS_* parameters")


@pytest.mark.slow
def test_a_long_flight_ranks_on_a_subsample_and_says_so(tmp_path_factory):
    """300 s at 50 Hz: the candidates are refitted on a cell × time subsample, said in the
    output, and the motor field is still found on its channel."""
    _, track, cal = _log(tmp_path_factory, "long.bin", duration_s=300.0, motor_uT=MOTOR_UT,
                         motor_channel="rcou_c3")
    d = streamcal.diagnose(track, calibration=cal)
    out = d.to_dict()
    assert d.held.n_ranked < d.n and out["n_ranked"] == d.held.n_ranked
    top = out["candidates"][0]
    assert top["effect"] == "aux_interference" and top["significant"] and top["material"]
    assert next(iter(d.held.aux_channels)) == "rcou_c3"


def test_clean_log_top_candidate_is_not_a_motor_field(clean):
    _, track, cal = clean
    top = streamcal.diagnose(track, calibration=cal).to_dict()["candidates"][0]
    assert not (top["effect"] == "aux_interference" and top["significant"] and top["material"])


def test_log_without_its_motor_channel_does_not_invent_one(motor):
    _, (_, track, cal) = motor
    bare = Track({k: v for k, v in track.columns.items() if k not in track.aux_names},
                 track.metadata)
    assert not bare.aux_names
    d = streamcal.diagnose(bare, calibration=cal)
    assert all(c.effect != "aux_interference" for c in d.candidates)
    assert d.held.aux_channels == {}


def test_every_reestimated_parameter_is_determined_and_plausible(clean):
    _, track, cal = clean
    d = streamcal.diagnose(track, calibration=cal)
    r = field_radius(cal.K)
    assert d.held.tolerance == pytest.approx(0.005 * r)
    # a yaw slice with 12° tilts determines the hard iron and the horizontal soft iron only
    assert {"b_x", "b_y", "b_z"} <= set(d.held.estimated) and "K_zz" in d.held.parameters
    for name, est in d.held.estimated.items():
        assert est["sigma"] <= d.held.tolerance, (name, est)
        lo, hi = plausible_range(name, r, cal.b)
        assert lo <= est["value"] <= hi, (name, est, (lo, hi))
        assert name not in d.held.parameters
    assert not d.held.suspicious
    out = json.loads(json.dumps(d.to_dict(), allow_nan=False, default=lambda v: None))
    st = out["fit_status"]
    assert st["status"] in STATUSES and st["iterations"] >= 1 and st["message"]
    for h in out["held_after_fit"]:
        assert h["parameter"] in out["held"] and h["parameter"] not in out["estimated"]
        lo, hi = h["range"]
        outside = max(lo - h["value"], h["value"] - hi, 0.0)
        assert h["sigma"] > out["tolerance"] or outside > SUSPICIOUS_SIGMAS * h["sigma"]


def test_cli_cal_autopilot_names_its_source_and_says_how_the_held_fit_ended(clean, capsys):
    path, _, _ = clean
    assert main(["diagnose", str(path), "--cal", "autopilot", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["calibration_source"].startswith("autopilot calibration in force")
    assert "COMPASS_*" in out["calibration_source"]
    assert main(["diagnose", str(path), "--cal", "autopilot"]) == 0
    text = capsys.readouterr().out
    assert "held fit   " in text and " iterations" in text


def test_cal_log_on_a_track_without_autopilot_parameters_exits_2(tmp_path, capsys):
    sim = flight_slice(10.0, seed=6)
    track = tmp_path / "plain.csv"
    Track.from_arrays(t=sim.t_mag, mag=sim.mag_uT, metadata={"mag_unit": "uT"}).write(track)
    assert main(["diagnose", str(track), "--cal", "log"]) == 2
    err = capsys.readouterr().err
    assert "--cal log" in err and "no autopilot compass calibration" in err
    assert "ArduPilot COMPASS_*" in err and "PX4 CAL_MAGn_*" in err


def test_report_against_a_calibration_file_shows_aux_figure_and_held_table(motor, tmp_path):
    _, (path, track, cal) = motor
    cal_path = tmp_path / "autopilot.json"
    cal.save(cal_path)
    out = tmp_path / "out.html"
    assert main(["report", str(path), "--cal", str(cal_path), "-o", str(out)]) == 0
    page = out.read_text()
    assert 'id="fig-aux_residuals"' in page and 'id="held-parameters"' in page
    table = page[page.index('id="held-parameters"'):]
    table = table[:table.index("</table>")]
    for name in ("K_xx", "K_zz", "b_x", "b_z"):
        assert f"<td>{name}</td>" in table
    assert "held" in table and "re-estimated" in table
