"""``streamcal demo`` end to end: the bundled track through the fake-bus driver and the streaming
calibrator, then the diagnosis names the hidden effect and the report is written."""
import importlib.util
import re
from pathlib import Path

import pytest

from streamcal.cli import main

REPO = Path(__file__).resolve().parent.parent


def _hidden_effect() -> str:
    """The effect the demo track's generator hid (tools/make_demo_track.py)."""
    spec = importlib.util.spec_from_file_location("make_demo_track", REPO / "tools" / "make_demo_track.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    (effect,) = module.HIDDEN
    return effect


@pytest.mark.slow
def test_demo_finds_the_hidden_effect_and_writes_the_report(tmp_path, capsys):
    assert main(["demo", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    accepted = re.findall(r"calibration #(\d+) accepted: coverage +(\d+)%, rms ([\d.]+) µT, "
                          r"field ([\d.]+) µT", out)
    assert len(accepted) >= 2
    coverages = [int(c) for _, c, _, _ in accepted]
    assert max(coverages) > min(coverages)          # printed as coverage grows
    hidden = _hidden_effect()
    assert f"misses {hidden}:" in out
    table = out.split("rank candidate", 1)[1]
    assert re.search(rf"^1 +{hidden} ", table, re.M)
    # the ladder reaches the noise floor once the effect is added
    ladder = re.search(rf"\+ {hidden} +([\d.]+) +([\d.]+)× floor", out)
    assert ladder and float(ladder.group(2)) <= 1.15
    assert "coverage" in out and "█" in out and "underside (−Z)" in out   # the terminal map
    report = tmp_path / "streamcal-demo-report.html"
    assert report.is_file() and str(report.resolve()) in out
    page = report.read_text()
    assert hidden in page and "calibrations accepted as coverage grew" in page


@pytest.mark.slow
def test_demo_quiet_prints_little(tmp_path, capsys):
    out_file = tmp_path / "sub" / "r.html"
    track = tmp_path / "t.csv.gz"
    from streamcal.sim import simulate

    simulate(30.0, 3, effects={"time_drift": 0.06}).track.write(track)
    assert main(["demo", "--track", str(track), "--quiet", "-o", str(out_file)]) == 0
    out = capsys.readouterr().out
    assert "accepted" not in out and "rank candidate" not in out
    assert "misses time_drift:" in out and out_file.is_file()
