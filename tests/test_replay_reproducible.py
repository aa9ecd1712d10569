"""``streamcal replay`` is reproducible: fits run when they are due (not on a worker thread while
ingest goes on) unless ``--realtime``/``--async-fits``, and each coverage milestone's line and map
come from one coverage computation."""
import json
import re
from pathlib import Path

import pytest

import streamcal
from streamcal.cli import main

from .conftest import REAL_TRACKS, real_path

TIVA_06 = REAL_TRACKS / "tiva_mpu9250_mag_06.csv"
DEMO = Path(streamcal.__file__).parent / "data" / "demo_track.csv.gz"


def _replay(capsys, *argv):
    code = main(["replay", *map(str, argv)])
    return code, capsys.readouterr().out


def _runs(capsys, track, *flags, n=3):
    return [_replay(capsys, track, *flags) for _ in range(n)]


@pytest.mark.slow
@pytest.mark.parametrize("track", [TIVA_06, DEMO], ids=["tiva_06", "demo"])
def test_three_json_replays_are_identical(track, capsys):
    runs = _runs(capsys, real_path(track), "--json")
    assert all(code == 0 for code, _ in runs)
    assert runs[0][1] == runs[1][1] == runs[2][1]
    summary = json.loads(runs[0][1].splitlines()[-1])
    assert summary["event"] == "summary" and summary["accepted"] >= 1
    assert summary["fits"] == summary["accepted"] + summary["rejected"] + summary["failed"]


def test_three_text_replays_are_identical_and_coverage_lines_agree(capsys):
    runs = _runs(capsys, DEMO)
    assert runs[0] == runs[1] == runs[2]
    lines = runs[0][1].splitlines()
    events = [i for i, line in enumerate(lines) if re.search(r"\] coverage +coverage", line)]
    assert events
    for i in events:
        pct, gap, hint = re.search(r"coverage (\d+)% of the sphere; largest gap (\d+)°: (.*)$",
                                   lines[i]).groups()
        # the map printed right after: its head and hint are the event's own figures
        assert lines[i + 1].startswith(f"coverage {pct}% of the sphere (")
        j = next(k for k in range(i + 1, len(lines)) if lines[k].startswith("hint: "))
        text, k = lines[j][len("hint: "):], j + 1
        while k < len(lines) and lines[k].startswith("      "):     # the wrapped hint
            text += " " + lines[k].strip()
            k += 1
        assert text == hint
        legend = lines[j - 1]
        if "largest gap (" in legend:
            assert f"largest gap ({gap}°)" in legend


def test_fits_are_synchronous_unless_realtime_or_async(monkeypatch, capsys):
    import streamcal.stream as stream

    seen = []
    real = stream.StreamingCalibrator

    def spy(*args, **kwargs):
        seen.append(kwargs.get("synchronous"))
        return real(*args, **kwargs)

    monkeypatch.setattr(stream, "StreamingCalibrator", spy)
    for flags in ([], ["--async-fits"], ["--sync-fits"]):
        _replay(capsys, DEMO, "--json", "--block", "100000", *flags)
    assert seen == [True, False, True]
    assert main(["replay", str(DEMO), "--sync-fits", "--async-fits"]) == 2
    assert "choose one" in capsys.readouterr().err
