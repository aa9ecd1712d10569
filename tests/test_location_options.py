"""``--lat/--lon/--alt-km/--date`` are checked before any reading, fitting or device: every
command that takes them says a bad one in one line, exit 2.

The recording named does not exist: a command that read (or opened a device) before checking
the place would name the missing file instead of the option."""
from __future__ import annotations

import pytest

from streamcal.cli import main

MISSING = "no-such-recording.csv"

#: Every command taking the location options, on a recording that is not there.
COMMANDS = {
    "fit": ["fit", MISSING],
    "fit --cal": ["fit", MISSING, "--cal", "autopilot"],
    "fit --heading": ["fit", MISSING, "--heading", "90"],
    "fit --attitude": ["fit", MISSING, "--attitude"],
    "diagnose": ["diagnose", MISSING],
    "diagnose --compass all": ["diagnose", MISSING, "--compass", "all"],
    "report": ["report", MISSING, "-o", "-"],
    "report --compass all": ["report", MISSING, "--compass", "all", "-o", "-"],
    "check": ["check", "autopilot", MISSING],
    "replay": ["replay", MISSING],
    "daemon": ["daemon", "--bus", f"fake:{MISSING}", "--no-socket"],
    "serial": ["serial", "--port", f"fake:{MISSING}", "--no-socket"],
}

#: Bad options → the words of the one line.
BAD = {
    "latitude": (["--lat", "91", "--lon", "0"], "--lat: expected degrees in -90..90"),
    "longitude": (["--lat", "0", "--lon", "400"], "--lon: expected degrees in -180..360"),
    "lat alone": (["--lat", "45"], "--lat and --lon go together"),
    "height": (["--lat", "0", "--lon", "0", "--alt-km", "900"], "--alt-km: the model covers"),
    "date format": (["--date", "2025-13-01"], "--date: expected YYYY-MM-DD"),
    "date outside the models": (["--lat", "0", "--lon", "0", "--date", "1990-06-01"],
                                "--date 1990-06-01: WMM2010 covers"),
}


@pytest.mark.parametrize("bad", BAD, ids=list(BAD))
@pytest.mark.parametrize("command", COMMANDS, ids=list(COMMANDS))
def test_bad_place_or_date_is_said_before_reading(command, bad, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("STREAMCAL_STATE_DIR", str(tmp_path / "state"))
    options, words = BAD[bad]
    assert main(COMMANDS[command] + options) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert words in err and MISSING not in err, err


def test_a_good_place_still_reaches_the_recording(capsys, tmp_path, monkeypatch):
    """The check lets a valid place through: the error is then the missing recording."""
    monkeypatch.chdir(tmp_path)
    assert main(["fit", MISSING, "--lat", "43", "--lon", "21", "--date", "2025-07-01"]) == 2
    assert MISSING in capsys.readouterr().err
