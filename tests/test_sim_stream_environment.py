"""Environment changes in the streaming calibrator on simulated sessions: the two tests of
tests/test_stream_environment.py (imported below, so their bodies and time windows are the same)
with their real recordings replaced by simulated ones of one sensor.

- ``broad``: a calibration from a full tumble of the sensor, and a 140 s session turned over a
  band of directions (a quarter of the sphere: never enough for a refit, as BROAD 32) with a
  magnet riding on the board — a constant offset in body axes — from 37 s to 95 s.
- ``sunsided``: two full sessions of one board whose hard iron differs by 12.6 µT, the second
  replayed after the first.
"""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.fitting import fit
from streamcal.inputs.track import Track
from streamcal.sim import simulate

from .test_stream_environment import (  # noqa: F401  (collected here, with the fixtures below)
    test_broad32_magnet_detected_forgotten_and_recovered,
    test_sunsided_session_change_detected_and_recalibrated)

K_TRUE = np.array([[46.0, 0.9, -1.2], [0.0, 44.5, 0.7], [0.0, 0.0, 49.5]])
B_TRUE = np.array([10.0, -6.0, 3.0])
MAGNET_UT = np.array([18.0, -14.0, 22.0])
MAGNET_SPAN = (37.0, 95.0)


def _session(duration, seed, b=B_TRUE, **kw):
    return simulate(duration, seed, K=K_TRUE, b=b, motor=False, temp_profile="constant",
                    imu_rate_hz=100.0, **kw).track


def _with_magnet(track: Track) -> Track:
    cols = {k: np.array(v) for k, v in track.columns.items()}
    on = track.mag_rows & (track.t >= MAGNET_SPAN[0]) & (track.t < MAGNET_SPAN[1])
    for i, k in enumerate(("mx", "my", "mz")):
        cols[k][on] += MAGNET_UT[i]
    return Track(cols, track.metadata)


@pytest.fixture(scope="module")
def broad():
    before = fit(_session(120.0, 61))
    return before, _with_magnet(_session(140.0, 62, coverage="band"))


@pytest.fixture(scope="module")
def sunsided():
    return _session(90.0, 63), _session(120.0, 64, b=B_TRUE + np.array([12.0, 0.0, -4.0]))
