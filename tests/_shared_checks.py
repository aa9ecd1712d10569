"""Checks that a real-data test and its simulated stand-in both run, each on its own data.

Each function asserts one behaviour on what it is given (a diagnosis, a log's path, a replayed
track); the real-data test (tests/conftest.py fixtures) and the simulated one call the same
function, so the two cannot drift apart."""
from __future__ import annotations

import html
import json
import re

import numpy as np
import pytest

from streamcal.cli.diagnose import _text
from streamcal.diagnosis.verdict import FLOOR_FACTOR
from streamcal.report import render_html
from streamcal.report.html import _SCALES_NOTE


def diagnosis_json(d) -> dict:
    """The diagnosis as its JSON output reads it (NaN as null)."""
    return json.loads(json.dumps(d.to_dict(), allow_nan=False, default=lambda v: None))


def check_unexplained_above_a_measured_floor(track, d) -> tuple[dict, str]:
    """An rms several times a measured floor that no candidate explains is ``unexplained``, and
    the misfit is located: every grouping partitions the inlier energy and the samples.
    Returns the JSON and the text output."""
    js = diagnosis_json(d)
    assert js["noise_floor_reliable"] is True and js["noise_floor"] > 0
    assert js["rms"] / js["noise_floor"] > FLOOR_FACTOR
    assert not any(c["significant"] and c["material"] for c in js["candidates"])
    assert js["verdict"] == "unexplained"
    assert f"{FLOOR_FACTOR:g}×" in js["noise_floor_rule"]
    text = _text(d)
    assert "unexplained" in text and js["noise_floor_rule"] in text
    misfit = js["misfit"]
    groups = [misfit["time"], misfit["directions"], misfit["rotation_rate"]["bins"],
              *misfit["covariates"].values()]
    for bins in groups:
        assert sum(b["share"] for b in bins) == pytest.approx(1.0, abs=1e-9)
        assert sum(b["samples"] for b in bins) == pytest.approx(1.0, abs=1e-9)
        assert all(0 <= b["share"] <= 1 for b in bins)
    # the energy is the one rms is computed from: rms² = energy / n over the same inliers
    assert np.sqrt(misfit["energy"] / misfit["n"]) == pytest.approx(js["rms"], rel=1e-9)
    assert misfit["n"] == js["n"] - js["n_outliers"]
    # time bins cover the recording in order
    starts = [b["t"][0] for b in misfit["time"]]
    assert starts == sorted(starts) and starts[0] == pytest.approx(float(track.t_mag[0]), abs=0.1)
    return js, text


def check_held_verdict_follows_the_same_rules(d) -> None:
    """Diagnosed against a calibration, well above a measured floor with no effect both
    significant and material: ``unexplained``, the misfit located, materiality on the floor
    the verdict uses."""
    js = diagnosis_json(d)
    assert js["held"] is not None and js["noise_floor_reliable"] is True
    assert js["rms"] > FLOOR_FACTOR * js["noise_floor"]
    assert not any(c["significant"] and c["material"] for c in js["candidates"])
    assert js["verdict"] == "unexplained"
    assert js["misfit"]["n"] == js["n"] - js["n_outliers"]
    for c, obj in zip(js["candidates"], d.candidates):
        assert obj.significant == (c["significant"] and c["material"])


def check_unmeasurable_floor_is_null_with_its_reason(track, d) -> tuple[list[str], float]:
    """A floor the recording cannot measure (3.33 Hz, turned by hand) is null with its reason,
    the verdict never ``at_noise_floor``, and no output states a ratio to it. Returns the three
    outputs (JSON, text, page) with the rules taken out, and the rms / measured-noise ratio."""
    js = d.to_dict()
    assert js["noise_floor"] is None and js["noise_floor_reliable"] is False
    reason = js["noise_floor_reason"]
    assert "3.33 Hz" in reason and "correlate" in reason
    assert js["noise"]["measured"] > js["rms"]    # what the estimate gave: above the rms
    assert js["verdict"] == "unexplained"         # never at_noise_floor without a floor
    out = json.dumps(js, allow_nan=False, default=lambda v: None)
    text = _text(d)
    page = render_html(track, d, figures=[])
    ratio = js["rms"] / js["noise"]["measured"]
    outputs = []
    for shown in (out, text, page):
        # the rules and the note on the tied residuals state factors, not ratios to a floor
        for rule in (js["noise_floor_rule"], js["significance_rule"], _SCALES_NOTE):
            shown = shown.replace(rule, "").replace(html.escape(rule), "")
        assert "× floor" not in shown and "× the floor" not in shown
        assert "× the noise floor" not in shown
        assert not re.search(r"\d\.\d\d×", shown), re.search(r".{40}\d\.\d\d×.{20}", shown)
        # the ratio as a number of its own (not the first digits of another one)
        assert not re.search(rf"(?<![\d.]){ratio:.2f}(?!\d)", shown)
        outputs.append(shown)
    assert "not measurable" in text and reason in text
    assert "cannot be measured" in page
    return outputs, ratio


def check_significance_and_materiality_apart(d) -> None:
    """time_drift significant (p < 1e-6) but not material (rms down by less than 10 %): the
    text shows both tests and the rule with its numbers."""
    js = d.to_dict()
    drift = next(c for c in js["candidates"] if c["effect"] == "time_drift")
    assert drift["p_value"] < 1e-6 and drift["significant"] is True
    assert drift["rms_after"] > 0.9 * drift["rms_before"] and drift["material"] is False
    for c in js["candidates"]:
        assert c["residual"] in ("sensor", "gravity_tied", "gyro_tied")
        assert c["significant"] == (c["p_value"] < 1e-6)
    rule = js["significance_rule"]
    assert "1e-06" in rule and "10%" in rule and "effective" in rule
    text = _text(d)
    assert rule in text and "not significant" not in text
    line = next(l for l in text.splitlines() if l.startswith("time_drift"))
    assert re.search(r"\byes\s+no\b", line), line


def check_tied_fit_names_both_residuals(text: str) -> None:
    """``fit --add time_lag`` output: the gravity-tied rms printed with its name beside the same
    calibration's (smaller) sensor-residual rms, and no unlabelled rms."""
    tied = re.search(r"rms\s+([\d.]+) µT on the gravity-tied residual", text)
    sensor = re.search(r"rms\s+([\d.]+) µT on the sensor residual", text)
    assert tied and sensor, text
    assert float(sensor.group(1)) < float(tied.group(1))
    assert not re.search(r"rms\s+[\d.]+ µT over", text)


def check_fit_json_names_the_residual(path, capsys) -> None:
    """``fit --json``: a plain fit is on the sensor residual; with mag_accel_misalignment on
    the gravity-tied one, with the sensor-residual rms beside it."""
    from streamcal.cli import main

    assert main(["fit", str(path), "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["residual"] == "sensor" and "rms_sensor" not in plain
    assert main(["fit", str(path), "--add", "mag_accel_misalignment", "--json"]) == 0
    tied = json.loads(capsys.readouterr().out)
    assert tied["residual"] == "gravity_tied"
    assert tied["rms_sensor"] > 0 and tied["rms_sensor"] != tied["rms"]


def check_report_heading_names_the_file(path, out) -> int:
    """``report``'s heading names the recording's file, not its folder. Returns the exit code."""
    from streamcal.cli import main

    code = main(["report", str(path), "-o", str(out)])
    heading = re.search(r"<h1>(.*?)</h1>", out.read_text()).group(1)
    assert path.name in heading and str(path.parent) not in heading
    return code
