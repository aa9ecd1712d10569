"""Every compass of a flight log (SPEC §6): --compass N|all on self-made DataFlash logs with two
and three compasses and on the real logs; the compass comparison against figures computed from
the logs' truth; throttle from CTUN and RCOU for COMPASS_MOTCT = 1."""
import json

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.diagnosis.compass_consistency import LIMITS
from streamcal.errors import InputError
from streamcal.inputs import autopilot_calibration, read_compasses, read_recording

from ._dataflash_log import write_flight

OFS = [(30.0, -20.0, 10.0), (-50.0, 40.0, 5.0), (12.0, 7.0, -30.0)]
ERR1 = np.array([150.0, 0.0, 0.0])     # mG: compass 1's hard iron its calibration misses


def _angle(u, v):
    return np.degrees(np.arccos(np.clip(np.sum(u * v, 1) / np.linalg.norm(u, axis=1)
                                        / np.linalg.norm(v, axis=1), -1, 1)))


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    path = tmp_path_factory.mktemp("compasses") / "two.bin"
    truth = write_flight(path, [{"ofs": OFS[0]}, {"ofs": OFS[1], "err": ERR1}], motct=1,
                         mot=(20.0, -10.0, 30.0))
    return path, truth


@pytest.mark.parametrize("layout", ["old", "instance"])
def test_each_compass_with_its_own_parameters(tmp_path, layout):
    """MAG/MAG2/MAG3 or MAG.I: compass N's readings have its own COMPASS_OFSn undone and its
    --cal autopilot rebuilds the logged field."""
    path = tmp_path / f"three_{layout}.bin"
    truth = write_flight(path, [{"ofs": o} for o in OFS], layout=layout, noise_mG=0.0)
    for k, ofs in enumerate(OFS):
        track = read_recording(path, compass=k)
        assert track.metadata["compass_instance"] == str(k)
        assert track.metadata["compasses_in_log"] == "0,1,2"
        # raw = logged − ofs; logged = the true body field (no noise, rounded to 1 mG)
        np.testing.assert_allclose(track.mag * 10.0 + np.array(ofs), truth["field"], atol=0.51)
        cal = autopilot_calibration(track)
        np.testing.assert_allclose(cal.b, -np.array(ofs) / 10.0)
    assert read_recording(path).metadata["compass_instance"] == "0"
    with pytest.raises(InputError, match=r"no compass 3 .*0, 1, 2"):
        read_recording(path, compass=3)


def test_default_is_compass_primary(tmp_path):
    path = tmp_path / "primary.bin"
    write_flight(path, [{"ofs": OFS[0]}, {"ofs": OFS[1]}], extra_params={"COMPASS_PRIMARY": 1})
    assert read_recording(path).metadata["compass_instance"] == "1"


def test_ctun_throttle_makes_motct1_autopilot_cal_work(two, capsys):
    """The issue's ArduPilot 3.4 case: COMPASS_MOTCT = 1 and the throttle only in CTUN.ThO."""
    path, truth = two
    track = read_recording(path, compass=1)
    assert track.metadata["throttle_source"].startswith("CTUN.ThO")
    t = track.t[~np.isnan(track.columns["throttle"])]
    np.testing.assert_allclose(np.sort(track.columns["throttle"][~np.isnan(
        track.columns["throttle"])]), np.sort(truth["throttle"]), atol=1e-6)
    assert len(t) == len(truth["t"])
    assert main(["diagnose", str(path), "--compass", "1", "--cal", "autopilot", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "aux_interference" in out["model"]
    # the autopilot's correction rebuilt from COMPASS_OFS/MOT and CTUN's throttle gives back the
    # field it logged (the true body field; 3 mG noise, offsets rounded to 1 mG)
    from streamcal.diagnosis.compass_consistency import calibrated_field

    track0 = read_recording(path, compass=0)
    _, field = calibrated_field(track0, autopilot_calibration(track0))
    err = np.linalg.norm(field - truth["field"] / 10.0, axis=1)
    assert np.median(err) < 0.6 and np.max(err) < 2.5   # µT; noise 0.3 µT per axis


def test_rcou_throttle_when_ctun_has_none(tmp_path):
    path = tmp_path / "rcou.bin"
    truth = write_flight(path, [{"ofs": OFS[0]}], throttle_in="RCOU")
    track = read_recording(path)
    assert track.metadata["throttle_source"].startswith("RCOU C1,C2,C3,C4")
    got = track.columns["throttle"][~np.isnan(track.columns["throttle"])]
    # PWM rounded to 1 µs over a 1000 µs range
    np.testing.assert_allclose(got, np.clip(truth["throttle"], 0, 1), atol=0.6e-3)
    # a plane: the SERVOn_FUNCTION 70 channel over its SERVOn_MIN/MAX
    plane = tmp_path / "plane.bin"
    write_flight(plane, [{"ofs": OFS[0]}], throttle_in="RCOU",
                 extra_params={"SERVO3_FUNCTION": 70, "SERVO3_MIN": 1200, "SERVO3_MAX": 1800})
    track = read_recording(plane)
    assert track.metadata["throttle_source"].startswith("RCOU C3 (SERVO3_FUNCTION 70")
    got = track.columns["throttle"][~np.isnan(track.columns["throttle"])]
    pwm = np.round(1000 + 1000 * truth["throttle"])
    np.testing.assert_allclose(got, np.clip((pwm - 1200) / 600, 0, 1), atol=1e-9)


def test_consistency_against_the_truth(two, capsys):
    """diagnose --compass all: the autopilot-calibration angles equal those between the true
    logged fields (f and f + ERR1), streamcal's fit removes ERR1, JSON per SPEC §6."""
    path, truth = two
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [c["instance"] for c in out["compasses"]] == [0, 1]
    assert [c["device_id"] for c in out["compasses"]] == [97539, 97795]
    assert all(c["diagnosis"]["verdict"] for c in out["compasses"])
    pairs = {p["calibration"]: p for p in out["consistency"]}
    f = truth["field"]
    expected = _angle(f, f + ERR1)
    ap = pairs["autopilot"]
    assert ap["a"] == 0 and ap["b"] == 1 and ap["n"] == len(f)
    assert abs(ap["angle_deg_median"] - np.median(expected)) < 0.3
    assert abs(ap["angle_deg_p95"] - np.percentile(expected, 95)) < 0.5
    xy_len = np.linalg.norm(ERR1[:2]) / 10.0
    body_xy = _angle(np.c_[f[:, :2], np.zeros(len(f))], np.c_[f[:, :2] + ERR1[:2], np.zeros(len(f))])
    share = np.mean((expected > 90) | (body_xy > 60) | (xy_len > LIMITS["xy_length_uT"]))
    assert abs(ap["fraction_inconsistent"] - share) < 0.01 and share > 0
    assert pairs["streamcal"]["angle_deg_median"] < 0.2 * ap["angle_deg_median"]
    assert out["consistency_limits"] == {"angle_deg": 90.0, "xy_angle_deg": 60.0,
                                         "xy_length_uT": 20.0, "why": "no ArduPilot version in "
                                         "the log: the current limits assumed"}


def test_text_and_report_with_every_compass(two, tmp_path, capsys):
    path, _ = two
    assert main(["diagnose", str(path), "--compass", "all"]) == 0
    text = capsys.readouterr().out
    assert "compass 0 (device id 97539)" in text and "compass 1 (device id 97795)" in text
    assert "3-D angle 90 deg, body X-Y angle 60 deg" in text and "0–1  autopilot" in text
    html = tmp_path / "r.html"
    assert main(["report", str(path), "--compass", "all", "-o", str(html)]) == 0
    page = html.read_text()
    assert 'id="compasses"' in page and 'id="fig-compass-consistency"' in page
    plots = tmp_path / "plots"
    assert main(["diagnose", str(path), "--compass", "all", "--plots", str(plots)]) == 0
    assert (plots / "compass-consistency.png").read_bytes()[:4] == b"\x89PNG"
    assert list((plots / "compass_0").glob("*.png")) and list((plots / "compass_1").glob("*.png"))


def test_compass_all_refused_where_one_is_read(two, tmp_path, capsys):
    path, _ = two
    assert main(["convert", str(path), "--compass", "all", "-o", str(tmp_path / "o.csv")]) == 2
    assert "--compass all" in capsys.readouterr().err
    assert main(["convert", str(path), "--compass", "1", "-o", str(tmp_path / "o.csv")]) == 0
    assert read_recording(tmp_path / "o.csv").metadata["compass_instance"] == "1"


def test_compass_on_a_track_refused(tmp_path, capsys):
    track = tmp_path / "t.csv"
    track.write_text("t,mx,my,mz\n0,1,2,3\n0.1,1,2,3\n")
    assert main(["fit", str(track), "--compass", "0"]) == 2
    assert "--compass applies to autopilot logs" in capsys.readouterr().err
    assert main(["diagnose", str(track), "--compass", "all"]) == 2
    assert "--compass applies to autopilot logs" in capsys.readouterr().err


@pytest.mark.slow
def test_real_logs_every_compass(flight_dir, capsys):
    """The bundled ArduPilot logs define MAG2/MAG3 but log only MAG; the PX4 sample with two
    sensor_mag instances gives two compasses with their own CAL_MAGn by device id."""
    for name in ("ardupilot_erle_Erle-Brain3.BIN", "ardupilot_erle_PXFv2.0b_Rpi.BIN"):
        tracks = read_compasses(flight_dir / name)
        assert [t.metadata["compass_instance"] for t in tracks] == ["0"]
        with pytest.raises(InputError, match="no compass 1"):
            read_recording(flight_dir / name, compass=1)
    ulg = flight_dir / "px4_pyulog_sample_logging_tagged_and_default_params.ulg"
    tracks = read_compasses(ulg)
    assert [t.metadata["compass_instance"] for t in tracks] == ["0", "1"]
    assert [t.metadata["compass_device_id"] for t in tracks] == ["197388", "197644"]
    assert [t.metadata["mag_cal_params"] for t in tracks] == ["CAL_MAG0_", "CAL_MAG1_"]
    # too few samples to calibrate either (exit 1), but the two compasses of that board, each
    # with its CAL_MAGn, agree within a degree or two, and the output says why each was not fitted
    assert main(["diagnose", str(ulg), "--compass", "all", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert all(c["diagnosis"] is None and c["error"] for c in out["compasses"])
    (pair,) = out["consistency"]
    assert pair["calibration"] == "autopilot" and pair["n"] > 10
    assert pair["angle_deg_median"] < 3.0 and pair["fraction_inconsistent"] == 0.0
    # the Erle-Brain3 log (ArduPilot 3.4) logs its throttle in CTUN.ThO only
    eb = read_recording(flight_dir / "ardupilot_erle_Erle-Brain3.BIN")
    assert eb.metadata["throttle_source"].startswith("CTUN.ThO")


def test_px4_every_magnetometer_with_its_cal_magn(tmp_path, capsys):
    """Self-made ULog with two sensor_mag instances: each gets the CAL_MAGn of its device id,
    the default is the higher CAL_MAGn_PRIO, and with both calibrations right they agree."""
    from ._ulog_log import write_ulog

    path = tmp_path / "two.ulg"
    offsets = [(0.05, -0.1, 0.02), (-0.2, 0.1, 0.3)]
    truth = write_ulog(path, offsets, prio=(50, 75))
    assert read_recording(path).metadata["compass_instance"] == "1"
    for k, track in enumerate(read_compasses(path)):
        assert track.metadata["mag_cal_params"] == f"CAL_MAG{k}_"
        np.testing.assert_allclose(autopilot_calibration(track).b,
                                   100.0 * np.array(offsets[k]), atol=1e-5)
        np.testing.assert_allclose(track.mag / 100.0 - offsets[k], truth["field_g"], atol=1e-6)
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ap = next(p for p in out["consistency"] if p["calibration"] == "autopilot")
    assert ap["angle_deg_p95"] < 0.01 and ap["fraction_inconsistent"] == 0.0
    assert main(["diagnose", str(path), "--compass", "2"]) == 2
    assert "no magnetometer 2" in capsys.readouterr().err


def test_priority_order_of_ardupilot_4(tmp_path):
    """ArduPilot 4.x logs compasses in priority order: logged compass 0 is the one whose
    COMPASS_DEV_IDn equals COMPASS_PRIO1_ID, and its parameters are that set's (here OFS2)."""
    path = tmp_path / "prio.bin"
    a, b = OFS[0], OFS[1]
    swapped = {"COMPASS_DEV_ID": 97795, "COMPASS_DEV_ID2": 97539,
               "COMPASS_PRIO1_ID": 97539, "COMPASS_PRIO2_ID": 97795}
    swapped.update({f"COMPASS_OFS_{x}": v for x, v in zip("XYZ", b)})
    swapped.update({f"COMPASS_OFS2_{x}": v for x, v in zip("XYZ", a)})
    write_flight(path, [{"ofs": a}, {"ofs": b}], layout="instance", extra_params=swapped)
    first, second = read_compasses(path)
    assert first.metadata["compass_params_index"] == "1"
    assert first.metadata["compass_device_id"] == "97539"
    np.testing.assert_allclose(autopilot_calibration(first).b, -np.array(a) / 10.0)
    assert second.metadata["compass_params_index"] == "0"
    np.testing.assert_allclose(autopilot_calibration(second).b, -np.array(b) / 10.0)


def test_a_calibration_of_compass_1_exports_as_compass_1(tmp_path, capsys):
    """The tumbled log's compass 1, fitted, exports as COMPASS_OFS2_* (ArduPilot) — not as the
    first compass's parameters, which would overwrite compass 0's calibration when loaded —
    and as CAL_MAG1_* for PX4; a refinement against the autopilot's calibration too."""
    path = tmp_path / "two.bin"
    write_flight(path, [{"ofs": OFS[0]}, {"ofs": OFS[1], "err": ERR1}])
    cal_path = tmp_path / "c1.json"
    assert main(["fit", str(path), "--compass", "1", "-o", str(cal_path)]) == 0
    from streamcal.calibration import Calibration

    assert Calibration.load(cal_path).extra["compass_params_index"] == 1
    for fmt, want, not_want in (("ardupilot", "COMPASS_OFS2_X,", "COMPASS_OFS_X,"),
                                ("px4", "\tCAL_MAG1_XOFF\t", "CAL_MAG0_")):
        out = tmp_path / f"c1.{fmt}"
        assert main(["export", str(cal_path), "--format", fmt, "-o", str(out)]) == 0
        text = out.read_text()
        assert want in text and not_want not in text, text
    capsys.readouterr()
    refined = tmp_path / "r1.json"
    assert main(["fit", str(path), "--compass", "1", "--cal", "autopilot", "-o",
                 str(refined)]) == 0
    assert Calibration.load(refined).extra["compass_params_index"] == 1


def test_compass_all_at_the_given_place(two, capsys):
    """--lat/--lon are the place of every compass's heading error and local field (the log has
    no GPS: without them the horizontal field is the fitted one, the reference absent); each
    compass's next step names that compass."""
    import datetime
    import math

    from streamcal.geomag import wmm_field

    path, _ = two
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) == 0
    without = json.loads(capsys.readouterr().out)["compasses"]
    assert main(["diagnose", str(path), "--compass", "all", "--json", "--lat", "78",
                 "--lon", "15", "--date", "2025-06-01"]) == 0
    given = json.loads(capsys.readouterr().out)["compasses"]
    ref = wmm_field(78.0, 15.0, 0.0, datetime.date(2025, 6, 1))
    h = ref["intensity_uT"] * math.cos(math.radians(ref["inclination_deg"]))
    for k, (a, b) in enumerate(zip(without, given)):
        assert a["reference_field"]["source"] is None
        assert b["reference_field"]["source"] == ref["source"]
        he_a, he_b = a["diagnosis"]["heading_error_deg"], b["diagnosis"]["heading_error_deg"]
        assert abs(he_a["H_uT"] - 25.0) < 0.5           # the log's 50 µT at 60° dip, fitted
        assert he_b["H_uT"] == pytest.approx(h, rel=1e-9)
        rms = a["diagnosis"]["ladder"][0]["rms"]
        assert he_b["before"] == pytest.approx(math.degrees(math.atan2(rms, h)), rel=1e-6)
        step = b["diagnosis"]["next_step"]
        assert step is None or step[step.index("--compass") + 1] == str(k)


def test_report_with_every_compass_diagnosis(two, tmp_path, capsys):
    """report --compass all: a section per compass with its own verdict, next step, heading
    error and ladder (the figures the JSON gives), before the default compass's full page."""
    import re

    path, _ = two
    assert main(["diagnose", str(path), "--compass", "all", "--json"]) == 0
    compasses = json.loads(capsys.readouterr().out)["compasses"]
    html = tmp_path / "all.html"
    assert main(["report", str(path), "--compass", "all", "-o", str(html)]) == 0
    page = html.read_text()
    starts = [page.index(f'<section id="compass-{c["instance"]}">') for c in compasses]
    assert starts == sorted(starts) and starts[-1] < page.index('id="default-compass"')
    for c, start in zip(compasses, starts):
        section = page[start:page.index("</section>", start)]
        d = c["diagnosis"]
        assert f"device id {c['device_id']}" in section
        assert f"Verdict {d['verdict']};" in section
        assert f"--compass {c['instance']}" in section
        shown = re.search(r"Heading error: up to ([0-9.]+)°", section).group(1)
        assert float(shown) == pytest.approx(d["heading_error_deg"]["before"], abs=0.005)
        assert f"{d['ladder'][0]['rms']:.4g}" in section


def test_report_terminal_says_each_compass_as_diagnose_does(two, tmp_path, capsys):
    """report --compass all prints, per compass, what diagnose --compass all begins with: the
    compass, its verdict line and its local-field lines (the same text), then the table."""
    path, _ = two
    place = ["--lat", "78", "--lon", "15", "--date", "2025-06-01"]
    assert main(["diagnose", str(path), "--compass", "all", "--json", *place]) == 0
    compasses = json.loads(capsys.readouterr().out)["compasses"]
    assert main(["diagnose", str(path), "--compass", "all", *place]) == 0
    diagnosed = capsys.readouterr().out
    assert main(["report", str(path), "--compass", "all", "-o", str(tmp_path / "r.html"),
                 *place]) == 0
    blocks = capsys.readouterr().out.split("\n\n")
    assert blocks[len(compasses)].startswith("consistency")
    for c, block in zip(compasses, blocks):
        lines = block.splitlines()
        assert lines[0] == f"compass {c['instance']} (device id {c['device_id']})"
        assert lines[1].startswith(f"verdict    {c['diagnosis']['verdict']}   (rule: ")
        assert lines[2].startswith("reference  WMM") and "78.0000°, 15.0000°" in lines[2]
        assert lines[1] in diagnosed and "\n".join(lines[2:]) in diagnosed
