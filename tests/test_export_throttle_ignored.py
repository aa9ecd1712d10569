"""COMPASS_MOTCT 1 on a firmware that ignores it: ArduPlane and Rover never pass their throttle to
the compass library (only ArduCopter calls ``Compass::set_throttle``), so ``export`` of a
throttle motor term for such a firmware (the log's, or ``--firmware-version``) says in the
file and on stderr that it is not applied there."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.cli import main
from streamcal.export.ardupilot import throttle_ignored

from ._vehicle_logs import Compass, soft_iron, write_vehicle_log


@pytest.mark.parametrize("firmware, expected", [
    ("ArduPlane V4.3.5 (x)", "Plane 4.3"), ("ArduPlane V3.2.3", "Plane 3.2"),
    ("APM:Rover v3.1.2", "Rover 3.1"), ("ArduCopter V4.3.7", None), ("Copter 3.5", None),
    (None, None)])
def test_which_firmware_ignores_throttle(firmware, expected):
    assert throttle_ignored(firmware) == expected


@pytest.fixture(scope="module")
def throttle_fits(tmp_path_factory):
    """``fit LOG --cal autopilot --add aux_interference=throttle`` on a plane and a copter log
    (COMPASS_MOTCT 1 in force): each refit carries a throttle term, exported as MOTCT 1."""
    out = {}
    for vehicle in ("plane4", "copter4"):
        d = tmp_path_factory.mktemp(vehicle)
        c = Compass(A=soft_iron(3), b=np.array([6.0, -3.0, 10.0]))
        log = d / f"{vehicle}.bin"
        write_vehicle_log(log, vehicle, [c], seconds=60.0, motct=1)
        cal = d / "cal.json"
        assert main(["fit", str(log), "--cal", "autopilot", "--add",
                     "aux_interference=throttle", "-o", str(cal)]) == 0
        out[vehicle] = cal
    return out


def test_plane_log_throttle_term_said_ignored(throttle_fits, tmp_path, capsys):
    cal = throttle_fits["plane4"]
    assert Calibration.load(cal).extra["firmware"].startswith("ArduPlane V4.3.5")
    capsys.readouterr()
    parm = tmp_path / "plane.parm"
    assert main(["export", str(cal), "--format", "ardupilot", "-o", str(parm)]) == 0
    err = capsys.readouterr().err
    text = parm.read_text()
    assert "COMPASS_MOTCT,1" in text
    said = "COMPASS_MOTCT 1 (throttle): Plane 4.3 (the log's firmware) ignores it"
    assert f"# NOT EXPRESSED: {said}" in text
    assert f"streamcal export: ardupilot cannot express: {said}" in err
    # loaded into a copter instead: no such note
    assert main(["export", str(cal), "--format", "ardupilot", "--firmware-version",
                 "Copter 4.3"]) == 0
    assert "ignores it" not in capsys.readouterr().out


def test_copter_log_throttle_term_not_flagged(throttle_fits, capsys):
    capsys.readouterr()
    assert main(["export", str(throttle_fits["copter4"]), "--format", "ardupilot"]) == 0
    out = capsys.readouterr()
    assert "COMPASS_MOTCT,1" in out.out and "ignores it" not in out.out + out.err
    # the same calibration exported for a Rover: flagged, naming --firmware-version
    assert main(["export", str(throttle_fits["copter4"]), "--format", "ardupilot",
                 "--firmware-version", "Rover 4.2"]) == 0
    assert "Rover 4.2 (--firmware-version) ignores it" in capsys.readouterr().err
