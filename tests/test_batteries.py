"""Every battery's current is its own aux channel (issue #24 item 4, "per battery where there are
several"): a self-made ArduPilot log with BAT instances 0 and 1, and a motor field that follows
battery 2's current only, is diagnosed against its COMPASS_* parameters with aux_interference on
that channel."""
from __future__ import annotations

import numpy as np
import pytest

import streamcal
from streamcal.inputs import autopilot_calibration, read_recording

from ._selfmade_logs import MOTOR_DIRECTION, dataflash_bytes, df_message, flight_slice


def _two_battery_log(path, motor_uT: float):
    """The flight's log with a second battery (BAT I = 1) whose current swings independently of
    the first; ``motor_uT`` µT per 10 A of battery 2 added to the readings along one direction."""
    flight = flight_slice(90.0, 3)
    amps2 = 12.0 + 8.0 * np.sin(2 * np.pi * flight.t_ch / 13.0) ** 2
    at_mag = np.interp(flight.t_mag, flight.t_ch, amps2)
    flight.mag_uT = flight.mag_uT + motor_uT * (at_mag / 10.0)[:, None] * MOTOR_DIRECTION
    log = dataflash_bytes(flight, messages=("IMU", "BAT"))
    extra = b"".join(df_message("BAT", int(round(t * 1e6)) + 1000, 1, 15.1, a)
                     for t, a in zip(flight.t_ch, amps2))
    path.write_bytes(log + extra)
    return amps2


def test_each_battery_current_is_read(tmp_path):
    path = tmp_path / "two_batteries.bin"
    amps2 = _two_battery_log(path, 0.0)
    track = read_recording(path)
    assert {"battery_current_a", "battery2_current_a"} <= set(track.aux_names)
    got = np.asarray(track.columns["battery2_current_a"])
    got = got[np.isfinite(got)]
    np.testing.assert_allclose(np.sort(np.unique(got)), np.sort(np.unique(amps2.astype(np.float32))),
                               rtol=1e-6)


@pytest.mark.slow
def test_a_motor_field_on_battery_2_is_found_on_its_current(tmp_path):
    path = tmp_path / "two_batteries.bin"
    _two_battery_log(path, 3.0)
    track = read_recording(path)
    d = streamcal.diagnose(track, calibration=autopilot_calibration(track))
    top = d.candidates[0]
    assert d.verdict == "effect_missing" and top.effect == "aux_interference"
    assert next(iter(d.held.aux_channels)) == "battery2_current_a"   # the residual follows it most
    gains = {k: np.linalg.norm(v["g"])
             for k, v in top.calibration.effects["aux_interference"]["channels"].items()}
    assert gains["battery2_current_a"] == pytest.approx(0.3, rel=0.1)   # 3 µT per 10 A
    assert gains["battery_current_a"] < 0.05
    assert d.ladder[-1]["rms"] < 0.6 * d.ladder[0]["rms"]


def test_px4_second_battery_status_instance_is_its_own_channel(tmp_path):
    """A self-made ULog with battery_status instances 0 and 1 (a second subscription appended
    to the log, as PX4 adds one when a second battery monitor appears): instance 1's current is
    ``battery2_current_a``, with the values written."""
    import struct

    from ._selfmade_logs import TOPICS, _topic_struct, _umsg, ulog_bytes

    flight = flight_slice(30.0, 4)
    log = ulog_bytes(flight, topics=("sensor_combined", "battery_status"))
    fields = TOPICS["battery_status"]
    msg_id = 7                                   # not used by the log's own subscriptions
    extra = [_umsg(b"A", struct.pack("<BH", 1, msg_id) + b"battery_status")]
    amps2 = 3.0 + 2.0 * np.cos(2 * np.pi * flight.t_ch / 7.0)
    for t, a in zip(flight.t_ch, amps2):
        us = int(round(t * 1e6)) + 1_000_000
        extra.append(_umsg(b"D", struct.pack("<H", msg_id)
                           + _topic_struct(fields).pack(us, 16.0, a)))
    path = tmp_path / "two_batteries.ulg"
    path.write_bytes(log + b"".join(extra))
    track = read_recording(path)
    assert {"battery_current_a", "battery2_current_a"} <= set(track.aux_names)
    got = np.asarray(track.columns["battery2_current_a"])
    got = got[np.isfinite(got)]
    np.testing.assert_allclose(np.unique(got), np.unique(amps2.astype(np.float32)), rtol=1e-6)
    assert "battery2_current_a" in track.metadata["battery_channels"]
