"""firmware_bridge.mavlink_link over real loopback sockets, messages encoded by pymavlink: unit
conversions of each compass message, RAW_IMU's IMU by autopilot, a TCP peer that goes away and
comes back, and the service adapter's counters."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from firmware_bridge.mavlink_link import MavlinkLink, MavlinkSilent
from streamcal.errors import InputError

WAIT_S = 60.0


def _encoder(system: int = 1, component: int = 1):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    return mavlink, mavlink.MAVLink(None, srcSystem=system, srcComponent=component)


def _pack(mav, msg) -> bytes:
    """The bytes of ``msg``, with the sequence number advanced as ``MAVLink.send`` does."""
    data = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return data


def _udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _read_until(link, mag_rows: int, seconds: float = WAIT_S):
    """Blocks until ``mag_rows`` magnetometer rows arrived; returns them concatenated."""
    blocks, got = [], 0
    deadline = time.monotonic() + seconds
    while got < mag_rows and time.monotonic() < deadline:
        try:
            block = link.read_block(50, timeout=0.1)
        except MavlinkSilent:
            continue
        if block is not None:
            blocks.append(block)
            got += int(block.mag_valid.sum())
    assert got >= mag_rows, f"{got} of {mag_rows} rows in {seconds} s"
    cat = lambda name: np.concatenate([getattr(b, name) for b in blocks])  # noqa: E731
    return cat("t"), cat("mag"), cat("accel"), cat("gyro"), cat("temp")


def _send_udp(port: int, packets) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for p in packets:
            s.sendto(p, ("127.0.0.1", port))
            time.sleep(0.0005)


@pytest.mark.parametrize("compass", (1, 2))
def test_scaled_imu_units(compass):
    mavlink, mav = _encoder()
    port = _udp_port()
    link = MavlinkLink(f"mavlink:udpin:127.0.0.1:{port}", compass=compass, silence_s=0.5)
    try:
        encode = mav.scaled_imu2_encode if compass == 1 else mav.scaled_imu3_encode
        other = mav.scaled_imu3_encode if compass == 1 else mav.scaled_imu2_encode
        packets = [_pack(mav, mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                                   mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0))]
        for k in range(20):
            packets.append(_pack(mav, other(1000 + 10 * k, 0, 0, 0, 0, 0, 0, 9999, 9999, 9999,
                                            0)))
            packets.append(_pack(mav, encode(1000 + 10 * k, 1000, -500, 250, 100, -200, 3000,
                                             480 + k, -120, -3000, 2150)))
            packets.append(_pack(mav, mav.scaled_pressure_encode(1005 + 10 * k, 1013.0, 0.0,
                                                                 2345, 0)))
        _send_udp(port, packets)
        t, mag, accel, gyro, temp = _read_until(link, 20)
    finally:
        link.close()
    rows = np.all(np.isfinite(mag), axis=1)
    np.testing.assert_allclose(mag[rows][:, 0], 0.1 * (480 + np.arange(20)))    # mgauss → µT
    np.testing.assert_allclose(mag[rows][0, 1:], [-12.0, -300.0])
    np.testing.assert_allclose(accel[rows][0], np.array([1000, -500, 250]) * 9.80665e-3)
    np.testing.assert_allclose(gyro[rows][0], [0.1, -0.2, 3.0])                 # mrad/s → rad/s
    np.testing.assert_allclose(temp[np.isfinite(temp)], 23.45)
    np.testing.assert_allclose(t[rows], 1.0 + 0.01 * np.arange(20))            # time_boot_ms
    assert np.all(np.diff(t) >= 0)
    assert link.stats.lost == 0 and link.stats.heartbeats == 1 and link.autopilot == 12


@pytest.mark.parametrize("autopilot, imu", (("MAV_AUTOPILOT_ARDUPILOTMEGA", True),
                                            ("MAV_AUTOPILOT_PX4", False)))
def test_raw_imu_imu_only_from_ardupilot(autopilot, imu):
    mavlink, mav = _encoder()
    port = _udp_port()
    link = MavlinkLink(f"mavlink:udpin:127.0.0.1:{port}", compass=0)
    try:
        packets = [_pack(mav, mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                                   getattr(mavlink, autopilot), 0, 0, 0))]
        packets += [_pack(mav, mav.raw_imu_encode(2_000_000 + 20_000 * k, 0, 0, -1000, 0, 0, 0,
                                                  200, 100, -400)) for k in range(10)]
        _send_udp(port, packets)
        t, mag, accel, gyro, _ = _read_until(link, 10)
    finally:
        link.close()
    np.testing.assert_allclose(mag[0], [20.0, 10.0, -40.0])
    np.testing.assert_allclose(t, 2.0 + 0.02 * np.arange(10))                  # time_usec
    assert np.isfinite(accel).all() == imu and np.isnan(accel).all() == (not imu)
    if imu:
        np.testing.assert_allclose(accel[0], [0, 0, -9.80665])


def test_tcp_peer_gone_and_back_is_a_reconnection():
    mavlink, mav = _encoder()
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(WAIT_S)
    port = server.getsockname()[1]
    sessions = 2

    def serve():
        k = 0
        for _ in range(sessions):
            conn, _ = server.accept()
            with conn:
                for _ in range(30):
                    conn.sendall(_pack(mav, mav.scaled_imu2_encode(10 * k, 0, 0, 1000, 0, 0, 0,
                                                                   100, 0, 0, 0)))
                    k += 1
                    time.sleep(0.002)
                time.sleep(0.2)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    link = MavlinkLink(f"mavlink:tcp:127.0.0.1:{port}", compass=1, silence_s=1.0)
    errors = []
    try:
        got = 0
        deadline = time.monotonic() + WAIT_S
        while got < 60 and time.monotonic() < deadline:
            try:
                block = link.read_block(50, timeout=0.1)
            except MavlinkSilent as exc:
                errors.append(str(exc))
                time.sleep(0.05)
                continue
            got += 0 if block is None else int(block.mag_valid.sum())
    finally:
        link.close()
        thread.join(WAIT_S)
        server.close()
    assert got == 60
    assert link.stats.reconnects >= 1 and link.stats.link_drops >= 1
    assert any("closed the connection" in e for e in errors), errors
    assert link.stats.lost == 0         # the sender's sequence numbers run on across connections


def test_service_adapter_counts_and_says_silence():
    from streamcal.service.mavlink_blocks import MavlinkBlocks
    from streamcal.service.sources import SourceUnavailable

    port = _udp_port()
    source = MavlinkBlocks(f"mavlink:udpin:127.0.0.1:{port}", compass=0, silence_s=0.3)
    try:
        assert "RAW_IMU magnetometer" in source.description
        deadline = time.monotonic() + WAIT_S
        with pytest.raises(SourceUnavailable, match="no MAVLink message so far"):
            while time.monotonic() < deadline:
                source.read()
        counters = source.counters()
        assert counters["link_drops"] == 1 and counters["messages"] == 0
    finally:
        source.close()


def test_connection_strings():
    with pytest.raises(InputError, match="needs a connection"):
        MavlinkLink("mavlink:")
    with pytest.raises(InputError, match="--compass"):
        MavlinkLink("mavlink:udpin:127.0.0.1:0", compass=3)
    with pytest.raises(InputError, match="cannot open the MAVLink connection"):
        MavlinkLink("mavlink:tcp:127.0.0.1:1")
    from firmware_bridge.mavlink_link import parse_connection

    assert parse_connection("mavlink:/dev/ttyACM0,57600") == ("/dev/ttyACM0", 57600)
    assert parse_connection("mavlink:udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", None)


def test_serial_device_with_baud_in_the_connection():
    """A pseudo-terminal stands for the flight controller's USB port: ``DEVICE,BAUD``."""
    import os

    mavlink, mav = _encoder()
    master, slave = os.openpty()
    try:
        link = MavlinkLink(f"mavlink:{os.ttyname(slave)},57600", compass=0)
        assert link.baud == 57600
        data = _pack(mav, mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                               mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
        data += b"".join(_pack(mav, mav.raw_imu_encode(1_000_000 + 10_000 * k, 0, 0, -1000, 0, 0,
                                                       0, 300, -200, 100)) for k in range(25))
        os.write(master, data)
        t, mag, accel, _, _ = _read_until(link, 25)
        link.close()
    finally:
        os.close(master)
        os.close(slave)
    np.testing.assert_allclose(mag, np.tile([30.0, -20.0, 10.0], (25, 1)))
    np.testing.assert_allclose(accel[:, 2], -9.80665)
    assert link.stats.lost == 0 and link.stats.messages == 26


def test_only_the_first_vehicle_is_read():
    mavlink, first = _encoder(system=1)
    _, second = _encoder(system=2)
    port = _udp_port()
    link = MavlinkLink(f"mavlink:udpin:127.0.0.1:{port}", compass=1)
    try:
        packets = []
        for k in range(10):
            packets.append(_pack(first, first.scaled_imu2_encode(10 * k, 0, 0, 0, 0, 0, 0,
                                                                 100, 0, 0, 0)))
            packets.append(_pack(second, second.scaled_imu2_encode(10 * k, 0, 0, 0, 0, 0, 0,
                                                                   -900, 0, 0, 0)))
        _send_udp(port, packets)
        _, mag, _, _, _ = _read_until(link, 10)
        time.sleep(0.2)
        link.read_block(50, timeout=0.2)
    finally:
        link.close()
    np.testing.assert_allclose(mag[:, 0], 10.0)
    assert link.vehicle == 1 and link.stats.other_vehicles == 10
