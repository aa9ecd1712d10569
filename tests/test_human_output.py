"""What a person reads (issue #11 item 8): numbers with units and sensible digits, one spelling
of µT, short ``print(cal)``/``print(diagnosis)``, a pasteable demo command, ``--skip-bad-rows``
counted on every command that reads a track, ``--plots`` saying where, guard reasons saying
below or above, and a demo that leaves nothing in the current directory."""
from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from streamcal.cli import main
from streamcal.sim import simulate

#: A float printed with all its digits (``tau=0.010945823840833167``).
LONG_FLOAT = re.compile(r"\d\.\d{7,}")
#: The ASCII spelling of the microtesla as a word of human text.
ASCII_UT = re.compile(r"(?<![\w_])uT(?![\w_])")


@pytest.fixture(scope="module")
def sim_track(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "track.csv.gz"
    simulate(60.0, seed=5).track.write(path)
    return path


@pytest.fixture(scope="module")
def bad_track(tmp_path_factory) -> tuple[Path, list[int]]:
    """A 40 s simulated track with a non-number in ``mx`` on three data lines (1-based line
    numbers returned)."""
    path = tmp_path_factory.mktemp("bad") / "bad.csv"
    simulate(40.0, seed=6).track.write(path)
    lines = path.read_text().split("\n")
    header = next(i for i, line in enumerate(lines) if line.startswith("t,"))
    col = lines[header].split(",").index("mx")
    spoiled = []
    for k in (header + 30, header + 700, header + 1500):
        cells = lines[k].split(",")
        cells[col] = "oops"
        lines[k] = ",".join(cells)
        spoiled.append(k + 1)
    path.write_text("\n".join(lines))
    return path, spoiled


# -- 1. digits with units, through one helper ----------------------------------------------------
def test_quantities_carry_units_and_three_significant_digits():
    from streamcal.units import effect_params, quantity

    assert quantity(0.010945823840833167, "s") == "10.9 ms"
    assert quantity(-0.0004219102381388621, "s") == "-422 µs"
    assert quantity(np.radians(0.55), "rad") == "0.55°"
    assert quantity([51.0753, -0.0341234, 2.0], "uT") == "[51.1, -0.0341, 2] µT"
    assert effect_params("time_lag", {"tau": 0.010945823840833167}) == "tau 10.9 ms"
    text = effect_params("temperature_offset", {"T0": 24.123, "c": [0.12, -0.0341234, 0.05]})
    assert text == "T0 24.1 °C, c [0.12, -0.0341, 0.05] µT/°C"


@pytest.mark.slow
def test_fit_prints_the_time_lag_of_a_real_track_in_ms(real_tracks_dir, capsys):
    """broad_30 (real BROAD recording) is where ``tau=0.010945823840833167`` was printed."""
    path = real_tracks_dir / "broad_30_stationary_magnet_C.csv.gz"
    assert main(["fit", str(path), "--add", "time_lag"]) == 0
    out = capsys.readouterr().out
    lag = re.search(r"time_lag: tau (-?[\d.]+) ms", out)
    assert lag, out
    assert 1.0 < abs(float(lag.group(1))) < 100.0        # a lag of milliseconds, not seconds
    assert not LONG_FLOAT.search(out), out
    assert "tau=" not in out


def test_fit_text_of_a_thermal_effect_has_units(sim_track, capsys):
    assert main(["fit", str(sim_track), "--add", "temperature_offset"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"temperature_offset: T0 [\d.]+ °C, c \[[-\d., e]+\] µT/°C", out), out
    assert not LONG_FLOAT.search(out), out


# -- 2. one spelling of µT in text; JSON unchanged ---------------------------------------------
@pytest.mark.slow
def test_text_says_micro_tesla_and_json_keeps_its_keys(sim_track, capsys):
    assert main(["fit", str(sim_track), "--add", "time_lag"]) == 0
    fit_text = capsys.readouterr().out
    assert main(["diagnose", str(sim_track)]) == 0
    diag_text = capsys.readouterr().out
    for text in (fit_text, diag_text):
        assert "µT" in text and not ASCII_UT.search(text), text
    assert re.search(r"rms +[\d.]+ µT \(sensor residual, over the \d+ samples of the ladder\) "
                     r"+noise floor [\d.]+ µT", diag_text)
    assert main(["fit", str(sim_track), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["unit"] == "uT" and "field_uT" in data


# -- 3. print(cal), print(diagnosis) -----------------------------------------------------------
def test_print_calibration_is_short_and_keeps_value_semantics(sim_track):
    import streamcal
    from streamcal.calibration import Calibration
    from streamcal.inputs.track import Track

    cal = streamcal.fit(Track.read(sim_track))
    text, rep = str(cal), repr(cal)
    assert len(text.splitlines()) <= 8 and len(text) < 700, text
    assert "µT" in text and "on the sensor residual" in text and f"{cal.n}" in text
    assert f"{cal.n_outliers} outliers" in text and "coverage" in text
    assert "\n" not in rep and len(rep) < 200 and "sensor" in rep
    assert not LONG_FLOAT.search(text + rep)
    again = Calibration.from_json(cal.to_json())
    assert again == cal and hash(again) == hash(cal)
    assert cal.replace(b=cal.b + 1.0) != cal
    assert json.loads(cal.to_json())["K"] == [[float(v) for v in row] for row in cal.K]


def test_print_diagnosis_is_short_and_to_dict_is_unchanged(sim_track):
    import streamcal
    from streamcal.inputs.track import Track

    d = streamcal.diagnose(Track.read(sim_track))
    text, rep = str(d), repr(d)
    assert len(text) < 1200 and len(text.splitlines()) <= 10, text
    assert text.startswith(f"Diagnosis: {d.verdict}")
    assert "noise floor" in text and "µT" in text and "residual" in text
    assert d.candidates[0].effect in text
    assert "\n" not in rep and len(rep) < 200 and d.verdict in rep
    full = d.to_dict()    # the JSON keeps every field
    assert {"candidates", "ladder", "noise", "residual_families"} <= set(full)
    assert len(json.dumps(full, default=lambda v: None)) > 5 * len(text)


# -- 5. --skip-bad-rows on every command that reads a track ------------------------------------
@pytest.fixture(scope="module")
def sim_cal(sim_track, tmp_path_factory) -> Path:
    from streamcal.fitting import fit
    from streamcal.inputs.track import Track

    path = tmp_path_factory.mktemp("cal") / "cal.json"
    fit(Track.read(sim_track)).save(path)
    return path


def _commands(bad: Path, tmp: Path, cal: Path) -> dict[str, list[str]]:
    return {
        "fit": ["fit", str(bad)],
        "diagnose": ["diagnose", str(bad)],
        "report": ["report", str(bad), "-o", str(tmp / "r.html")],
        "replay": ["replay", str(bad)],
        "convert": ["convert", str(bad), "-o", str(tmp / "c.csv")],
        "apply": ["apply", str(cal), str(bad), "-o", str(tmp / "a.csv")],
        "batch": ["batch", "fit", str(bad), "--jobs", "1", "-o", str(tmp / "s.csv")],
        "record": ["record", "--bus", f"fake:{bad}", "-o", str(tmp / "rec.csv")],
        "daemon": ["daemon", "--bus", f"fake:{bad}", "--no-socket", "--sync-fits",
                   "--state-dir", str(tmp / "state")],
    }


@pytest.mark.parametrize("command", ["fit", "diagnose", "report", "replay", "convert", "apply",
                                     "batch", "record", "daemon"])
@pytest.mark.slow
def test_skip_bad_rows_counts_the_skipped_rows_on_stderr(command, bad_track, sim_cal,
                                                         tmp_path, capsys):
    bad, spoiled = bad_track
    argv = _commands(bad, tmp_path, sim_cal)[command]
    assert main(argv) != 0                                       # refused without the flag
    assert re.search(rf"\b{spoiled[0]}\b.*'mx'", capsys.readouterr().err)
    assert main(argv + ["--skip-bad-rows"]) in (0, 1)
    err = capsys.readouterr().err
    said = re.search(rf"skipped 3 bad rows of {re.escape(str(bad))} \(first: line "
                     rf"{spoiled[0]} column 'mx': ", err)
    assert said, err
    if command == "batch":
        import csv

        row = next(csv.DictReader((tmp_path / "s.csv").open()))
        assert row["status"] == "ok" and row["skipped_rows"] == "3"


# -- 6. diagnose --plots says where ------------------------------------------------------------
@pytest.mark.slow
def test_plots_say_where_and_how_many(sim_track, tmp_path, capsys):
    out_dir = tmp_path / "figs"
    assert main(["diagnose", str(sim_track), "--plots", str(out_dir)]) == 0
    said = re.search(r"^plots: (\d+) PNG files written to (.+)$", capsys.readouterr().out, re.M)
    assert said
    assert Path(said.group(2)) == out_dir.resolve()
    assert int(said.group(1)) == len(list(out_dir.glob("*.png"))) > 0
    assert main(["diagnose", str(sim_track), "--plots", str(out_dir), "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)                      # stdout stays one JSON object
    assert "written to" in captured.err


# -- 7. guard reasons say below or above -------------------------------------------------------
@pytest.mark.parametrize("scale, words", [(1.816 / 50.0, "below the lower limit 15 µT"),
                                          (3.0, "above the upper limit 100 µT")])
def test_field_out_of_range_says_which_side(scale, words):
    from streamcal.calibration import Calibration
    from streamcal.stream.guard import AcceptanceGuard

    cal = Calibration(K=np.eye(3) * 50.0 * scale, b=np.zeros(3), rms=0.01 * scale, n=100)
    decision = AcceptanceGuard().sanity(cal)
    assert decision is not None and decision.reason == "field_out_of_range"
    text = str(decision)
    assert words in text and f"field {50.0 * scale:.4g} µT is" in text, text
    assert decision.to_dict()["reason"] == "field_out_of_range"   # JSON as before


# -- 4 and 8. the demo: a pasteable command, nothing left in the current directory -------------
@pytest.mark.slow
def test_demo_leaves_the_cwd_clean_and_its_command_works(tmp_path, monkeypatch, capsys):
    track = tmp_path / "in" / "t.csv.gz"
    track.parent.mkdir()
    simulate(30.0, 3, effects={"time_drift": 0.06}).track.write(track)
    cwd = tmp_path / "repo"
    cwd.mkdir()
    git = shutil.which("git")
    if git:
        subprocess.run([git, "init", "-q", str(cwd)], check=True)
    monkeypatch.chdir(cwd)
    before = sorted(os.listdir(cwd))
    status = subprocess.run([git, "status", "--porcelain"], capture_output=True, text=True,
                            cwd=cwd).stdout if git else ""
    assert main(["demo", "--track", str(track), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert sorted(os.listdir(cwd)) == before
    if git:
        assert subprocess.run([git, "status", "--porcelain"], capture_output=True, text=True,
                              cwd=cwd).stdout == status
    report = Path(re.search(r"report written to (.+)$", out, re.M).group(1))
    try:
        assert report.is_file() and report.parent != cwd
        command = re.search(r"^next step \(gives the rms promised above\): (streamcal fit .+)$",
                            out, re.M).group(1)
        argv = shlex.split(command)[1:]
        assert Path(argv[1]).is_absolute() and Path(argv[1]).is_file()
        assert argv[2:] == ["--add", "time_drift"]
        assert command in report.read_text()      # the report suggests the same command
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        monkeypatch.chdir(elsewhere)              # pasted from another directory
        assert main(argv) == 0
        assert "time_drift: t0" in capsys.readouterr().out
    finally:
        shutil.rmtree(report.parent, ignore_errors=True)


@pytest.mark.slow
def test_report_command_names_the_track_as_given(sim_track, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(sim_track.parent)
    html = tmp_path / "r.html"
    assert main(["report", sim_track.name, "-o", str(html)]) == 0
    page = html.read_text()
    for path in re.findall(r"streamcal fit (\S+) --add", page):
        assert (sim_track.parent / path).is_file()
