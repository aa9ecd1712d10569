"""Logs of vehicles streamcal has no real log of (issue #24's acceptance runs on such flights):
self-made ArduCopter 3.3–4.x, ArduPlane 3.x/4.x and ArduRover 3.x/4.x logs
(:mod:`tests._vehicle_logs`) with two or three compasses, attitude and GPS, one or two batteries
whose current runs 0–70 A, and each firmware's own throttle message. Each is read and checked
against the truth it was written from."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.inputs import read_recording

from ._vehicle_logs import VEHICLES, Compass, soft_iron, write_vehicle_log


def _compasses(n: int) -> list[Compass]:
    return [Compass(A=soft_iron(k), b=np.array([12.0, -7.0, 20.0]) * (k + 1) / 2,
                    g=np.array([0.05, -0.02, 0.08]) * (1 - 0.4 * k)) for k in range(n)]


def _column(track, name):
    values = np.asarray(track.columns[name], float)
    return values[np.isfinite(values)]


@pytest.mark.parametrize("vehicle", ["copter4", "copter40", "copter36", "plane4", "rover4"])
def test_each_battery_is_its_own_channel(vehicle, tmp_path):
    """BAT's instance field is ``Inst`` (4.1 on) or ``Instance`` (4.0), BAT2 before: battery 0's
    current alone is ``battery_current_a`` (0–70 A), battery 1's is ``battery2_current_a`` —
    not the two batteries' rows mixed into one channel."""
    path = tmp_path / f"{vehicle}.bin"
    truth = write_vehicle_log(path, vehicle, _compasses(2), seconds=30.0, two_batteries=True)
    track = read_recording(path)
    np.testing.assert_allclose(_column(track, "battery_current_a"),
                               truth.current.astype(np.float32), rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(_column(track, "battery2_current_a"),
                               truth.current2.astype(np.float32), rtol=1e-6)


@pytest.mark.parametrize("vehicle, source", [
    ("copter4", "CTUN.ThO (0..1)"), ("copter33", "CURR.Throttle / 1000 (0..1)"),
    ("plane4", "CTUN.ThO / 100 (0..1; a plane's throttle, logged in percent)"),
    ("plane3", "CTUN.ThrOut / 100 (0..1; a plane's throttle, logged in percent)"),
    ("rover3", "CTUN.ThrOut / 100 (0..1; a rover's throttle, logged in percent)"),
    ("rover4", "THR.ThrOut / 100 (0..1; a rover's throttle, logged in percent)")])
def test_throttle_in_each_vehicles_units(vehicle, source, tmp_path):
    """The throttle each vehicle logs becomes 0..1: a copter's CTUN.ThO as is, CURR.Throttle
    /1000, a plane's CTUN.ThO/ThrOut and a rover's CTUN/THR.ThrOut (percent) /100 — not 100×
    or 10× off — and a rover's THR is read (not four RCOU channels that include its steering)."""
    path = tmp_path / f"{vehicle}.bin"
    truth = write_vehicle_log(path, vehicle, _compasses(2), seconds=30.0)
    track = read_recording(path)
    assert track.metadata["throttle_source"] == source
    # logged as float, int16 percent (0.01 steps) or int16 per mille (0.001 steps)
    np.testing.assert_allclose(_column(track, "throttle"), truth.throttle, atol=0.0051)
