"""Host link: loop:// and in-memory feeds, Raw: lines, and host ↔ fake board over a real pty."""
from __future__ import annotations

import os

import numpy as np
import pytest
import serial

from firmware_bridge import frames as fr
from firmware_bridge.fake_board import Faults, FakeBoard, sphere_sums_add
from firmware_bridge.ports import open_link
from streamcal.inputs.track import Track
from firmware_bridge.rawlines import RawLineReader, raw_to_si
from firmware_bridge.serial_link import LinkError, SerialLink
from streamcal.calibration import Calibration
from streamcal.errors import InputError

HELLO = fr.Hello(period_us=10000, accel_scale=0.001, gyro_scale=0.002, temp_scale=0.5, temp_offset=21.0,
                 mag_scale=(0.25, 0.125, 0.5))
CAL = Calibration(K=[[48.0, 1.5, -2.0], [0.0, 51.0, 0.75], [0.0, 0.0, 46.0]], b=[12.0, -7.5, 30.0])


def synthetic(n: int, seed: int = 0):
    """A rotating field of 50 µT with offsets; mag on every other row (IMU at twice the mag rate)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    mag = 50.0 * u @ np.diag([1.0, 1.1, 0.9]) + [12.0, -7.5, 30.0]
    mag[1::2] = np.nan
    accel = rng.normal(size=(n, 3)) + [0, 0, 9.81]
    gyro = rng.normal(scale=0.3, size=(n, 3))
    temp = 25.0 + 0.001 * np.arange(n)
    return t, mag, accel, gyro, temp


def drain(link: SerialLink, board: FakeBoard):
    """Read blocks until the board has replayed the track and the line is quiet."""
    blocks = []
    while True:
        block = link.read_block(timeout=0.3)
        if block is not None:
            blocks.append(block)
        elif board.finished.is_set():
            return blocks


def pty_link(board: FakeBoard) -> SerialLink:
    port = serial.Serial(board.port_name, 115200, timeout=0.02)
    link = SerialLink(port, source="serial:fake", board=board)
    link.wake()
    return link


# -- pure feeding / loop:// ---------------------------------------------------------------------

def test_samples_become_si_blocks_with_nan_where_invalid():
    link = SerialLink(serial.serial_for_url("loop://", timeout=0.01))
    valid = int(fr.Status.MAG_VALID | fr.Status.ACCEL_VALID | fr.Status.GYRO_VALID | fr.Status.TEMP_VALID)
    link.feed(fr.encode(HELLO, 0) + fr.encode(fr.Sample(t_us=1000, mag=(4, -8, 2), accel=(100, 0, -100),
                                                        gyro=(1, 2, 3), temp=4, status=valid), 1)
              + fr.encode(fr.Sample(t_us=2000, accel=(1, 1, 1), status=int(fr.Status.ACCEL_VALID)), 2))
    block = link.read_block(timeout=0.1)
    np.testing.assert_allclose(block.t, [0.001, 0.002])
    np.testing.assert_allclose(block.mag[0], [1.0, -1.0, 1.0])
    assert np.all(np.isnan(block.mag[1])) and np.all(np.isnan(block.gyro[1])) and np.isnan(block.temp[1])
    np.testing.assert_allclose(block.accel[0], [0.1, 0.0, -0.1], rtol=1e-6)
    np.testing.assert_allclose(block.gyro[0], [0.002, 0.004, 0.006], rtol=1e-6)
    assert block.temp[0] == 23.0
    assert link.mode == "frames" and link.stats.samples == 2 and link.stats.lost == 0


def test_board_clock_wrap_keeps_time_increasing():
    link = SerialLink(serial.serial_for_url("loop://", timeout=0.01))
    stamps = [0xFFFFFF00 - 10000, 0xFFFFFF00, 0x100, 0x100 + 10000]
    link.feed(fr.encode(HELLO, 0) + b"".join(fr.encode(fr.Sample(t_us=s), i + 1) for i, s in enumerate(stamps[:2])))
    first = link.read_block(timeout=0.05)
    link.feed(b"".join(fr.encode(fr.Sample(t_us=s), i + 3) for i, s in enumerate(stamps[2:])))
    second = link.read_block(timeout=0.05)
    t = np.concatenate([first.t, second.t])
    np.testing.assert_allclose(np.diff(t), [0.01, 0.000512, 0.01], atol=1e-9)


def test_samples_wait_for_hello_and_link_asks_for_it():
    port = serial.serial_for_url("loop://", timeout=0.01)
    link = SerialLink(port)
    link.feed(fr.encode(fr.Sample(t_us=5, status=0), 3))
    assert link.read_block(timeout=0.05) is None           # no scales yet; GET_INFO sent (and echoed)
    assert link.stats.unexpected >= 1                      # loop:// returned our own GET_INFO
    link.feed(fr.encode(HELLO, 4))
    assert len(link.read_block(timeout=0.05)) == 1


def test_loop_port_round_trip_through_pyserial():
    port = serial.serial_for_url("loop://", timeout=0.01)
    link = SerialLink(port)
    port.write(fr.encode(HELLO, 0) + b"".join(fr.encode(fr.Sample(t_us=i), i + 1) for i in range(50)))
    got = 0
    while (block := link.read_block(timeout=0.1)) is not None:
        got += len(block)
    assert got == 50 and link.stats.frames == 51 and link.stats.lost == 0


def test_command_without_answer_retries_then_raises():
    link = SerialLink(serial.serial_for_url("loop://", timeout=0.01))
    with pytest.raises(LinkError, match="no answer to Stop after 2 attempts"):
        link.stop(retries=1, timeout=0.1)
    assert link.stats.retries == 1


def test_open_reports_unusable_port():
    with pytest.raises(InputError, match="cannot open"):
        SerialLink.open("/nonexistent/ttyACM9")


# -- Raw: lines (MotionCal-style sketches) ------------------------------------------------------

def test_raw_lines_auto_detected_and_scaled_like_motioncal():
    link = SerialLink(serial.serial_for_url("loop://", timeout=0.01))
    link.feed(b"MotionCal sketch v1\r\nRaw:8192,0,-8192,16,-32,0,100,-250,0\r\nUni:1,2,3\r\n"
              b"Raw:0,0,8192,0,0,160,1,2,3\r\nRaw:1,2,3\r\n")
    assert link.mode == "raw"
    block = link.read_block(timeout=0.05)
    assert len(block) == 2
    np.testing.assert_allclose(block.accel[0], [9.80665, 0, -9.80665])
    np.testing.assert_allclose(block.gyro[0], np.deg2rad([1.0, -2.0, 0.0]))
    np.testing.assert_allclose(block.mag[0], [10.0, -25.0, 0.0])
    np.testing.assert_allclose(block.gyro[1], [0, 0, np.deg2rad(10.0)])
    assert link.stats.raw_lines == 2 and link.stats.bad_lines == 1


def test_raw_reader_is_bounded_and_split_anywhere():
    text = b"Raw:1,2,3,4,5,6,7,8,9\r\n" * 20 + b"x" * 1000 + b"\nRaw:-1,-2,-3,-4,-5,-6,-7,-8,-9\n"
    reader = RawLineReader()
    rows = np.concatenate([reader.feed(text[i:i + 7]) for i in range(0, len(text), 7)])
    assert rows.shape == (21, 9) and rows[-1, 0] == -1
    assert reader.stats.overlong == 1 and len(reader._buf) <= reader.max_line
    accel, gyro, mag = raw_to_si(rows[:1])
    np.testing.assert_allclose(mag, [[0.7, 0.8, 0.9]])


# -- host ↔ fake board over a pty ---------------------------------------------------------------

def test_every_frame_accounted_for_with_line_faults():
    faults = Faults(drop=0.02, corrupt=0.02, truncate=0.02, garbage=0.02, seed=7)
    with FakeBoard(*synthetic(3000), faults=faults) as board:
        link = pty_link(board)
        drain(link, board)
        report = link.query_calibration(timeout=0.5, retries=10)  # a last frame that arrives closes the count
        assert report.valid == 0
        stats = link.stats
        assert link.sequence.received + stats.lost == board.frames_sent
        assert stats.frames == link.sequence.received
        assert stats.lost > 0 and stats.crc_errors + stats.cobs_errors + stats.truncated > 0
        assert stats.garbage_bytes > 0
        link.close()


def test_calibration_reaches_eeprom_and_board_output_matches_host_apply():
    # The board streams from boot until STOP arrives; how many rows go by first depends on the
    # machine (200 on a loaded CI runner), so the track is long enough to leave > 900 mag rows after.
    with FakeBoard(*synthetic(6000)) as board:
        link = pty_link(board)
        link.stop()
        cal_id = link.send_calibration(CAL)
        assert board.calibration is not None and board.calibration.cal_id == cal_id
        assert bytes(board.eeprom[:3]) == b"SC\x01"
        stored = fr.SetCalibration.unpack_body(bytes(board.eeprom[3:43]))
        K, b = stored.matrices()
        np.testing.assert_allclose(K, CAL.K, rtol=1e-7)
        np.testing.assert_allclose(b, CAL.b, rtol=1e-7)
        link.start()
        blocks = drain(link, board)
        t_cal, x_board = link.calibrated()
        mag = np.concatenate([blk.mag for blk in blocks])
        t = np.concatenate([blk.t for blk in blocks])
        # samples streamed between boot and STOP carry no calibrated output; all later ones do
        rows = np.all(np.isfinite(mag), axis=1) & (t >= t_cal[0])
        assert len(t_cal) == rows.sum() > 900
        np.testing.assert_array_equal(t_cal, t[rows])
        np.testing.assert_allclose(x_board, CAL.apply(mag[rows]), rtol=2e-6, atol=2e-6)
        assert link.stats.lost == 0
        link.close()


def test_calibration_survives_reboot_through_eeprom():
    with FakeBoard(*synthetic(10)) as board:
        link = pty_link(board)
        cal_id = link.send_calibration(CAL, cal_id=77)
        eeprom = bytes(board.eeprom)
        link.close()
    with FakeBoard(*synthetic(10), eeprom=eeprom) as rebooted:
        link = pty_link(rebooted)
        report = link.query_calibration()
        assert report.valid == 1 and report.cal_id == cal_id == 77
        assert link.hello.flags & fr.HelloFlags.CAL_LOADED
        link.clear_calibration()
        assert link.query_calibration().valid == 0 and rebooted.calibration is None
        link.close()


def test_board_refuses_damaged_calibration_block():
    with FakeBoard(*synthetic(10)) as board:
        link = pty_link(board)
        good = fr.SetCalibration.from_kb(CAL.K, CAL.b, cal_id=1)
        with pytest.raises(LinkError, match="BAD_CAL_CRC"):
            link._command(fr.SetCalibration(cal_id=1, k=good.k, b=good.b, crc=good.crc ^ 1), fr.Ack)
        bad_k = fr.SetCalibration.from_kb(np.diag([1.0, -1.0, 1.0]), [0, 0, 0], cal_id=2)
        with pytest.raises(LinkError, match="BAD_CAL_VALUES"):
            link._command(bad_k, fr.Ack)
        assert board.calibration is None and link.stats.naks == 2
        link.close()


def test_host_rejects_calibrations_the_board_cannot_apply():
    link = SerialLink(serial.serial_for_url("loop://", timeout=0.01))
    with pytest.raises(InputError, match="uT only"):
        link.send_calibration(CAL.replace(sensor="accel", unit="m/s^2"))
    with pytest.raises(InputError, match="K and b only"):
        link.send_calibration(CAL.replace(effects={"time_drift": {"c": [0, 0, 0]}}))


def test_sphere_sums_on_board_equal_sums_of_received_samples():
    with FakeBoard(*synthetic(1500)) as board:
        link = pty_link(board)
        blocks = drain(link, board)
        sums = link.sphere_sums
        mag = np.concatenate([blk.mag for blk in blocks])
        mag = mag[np.all(np.isfinite(mag), axis=1)]
        counts = np.round(mag / np.array(link.hello.mag_scale)).astype(np.int64)
        assert sums is not None and sums.n == 700                    # reported every 100 mag samples
        assert sums.values() == sphere_sums_add(fr.SphereSums(), counts[:sums.n + sums.rejected]).values()
        link.close()


def test_open_fake_track_file(tmp_path):
    from streamcal.inputs.track import Track

    t, mag, accel, gyro, temp = synthetic(400)
    path = tmp_path / "track.csv"
    Track.from_arrays(t, mag=mag, accel=accel, gyro=gyro, temp=temp).write(path)
    link = open_link(f"fake:{path}", timeout=0.02, read_track=Track.read)
    try:
        blocks = drain(link, link.board)
        got = np.concatenate([blk.mag for blk in blocks])
        assert len(got) == 400 and link.source == f"serial:fake:{path}"
        rows = np.all(np.isfinite(mag), axis=1)
        np.testing.assert_array_equal(np.all(np.isfinite(got), axis=1), rows)
        step = np.array(link.hello.mag_scale)
        assert np.all(np.abs(got[rows] - mag[rows]) <= step / 2 + 1e-4)   # quantised to AK8963 counts
        np.testing.assert_allclose(np.concatenate([blk.temp for blk in blocks]), temp, atol=0.002)
    finally:
        link.close()


# -- the same checks on a real board (opt-in: STREAMCAL_SERIAL_PORT=DEV; never in CI) ----------

@pytest.fixture(params=["fake", "real"])
def any_link(request):
    """A link to the fake board over a pty, or to ``$STREAMCAL_SERIAL_PORT`` (a board running
    arduino/streamcal_bridge; baud ``$STREAMCAL_SERIAL_BAUD``, default 115200) when set."""
    if request.param == "fake":
        board = FakeBoard(*synthetic(4000)).start()
        link = pty_link(board)
    else:
        spec = os.environ.get("STREAMCAL_SERIAL_PORT")
        if not spec:
            pytest.skip("real-hardware check: set STREAMCAL_SERIAL_PORT=/dev/ttyACM0 to run it against a "
                        "board running arduino/streamcal_bridge")
        link = open_link(spec, int(os.environ.get("STREAMCAL_SERIAL_BAUD", "115200")))
    yield link
    link.close()


def test_any_board_identifies_itself_and_streams_plausible_samples(any_link):
    from firmware_bridge import registers as R

    hello = any_link.request_info()
    assert R.WHO_AM_I_TABLE[hello.whoami].has_magnetometer and hello.ak_wia == R.AK8963_WIA
    assert hello.flags & fr.HelloFlags.MAG_PRESENT and hello.period_us >= 2000
    assert all(0 < s < 1.5 * R.mag_scale(16) for s in hello.mag_scale)          # × ASA factor
    blocks, n = [], 0
    for block in any_link.blocks(idle_timeout=3.0):
        blocks.append(block)
        n += len(block)
        if n >= 400:
            break
    assert n >= 400
    t = np.concatenate([b.t for b in blocks])
    mag, accel, gyro, temp = (np.concatenate([getattr(b, k) for b in blocks]) for k in ("mag", "accel", "gyro", "temp"))
    assert np.all(np.diff(t) > 0)
    has_mag = np.all(np.isfinite(mag), axis=1)
    assert has_mag.sum() >= n // 4 and np.all(np.abs(mag[has_mag]) <= 1.5 * R.MAG_FULL_SCALE_UT)
    has_imu = np.all(np.isfinite(accel), axis=1) & np.all(np.isfinite(gyro), axis=1)
    assert has_imu.sum() >= n // 2
    assert np.all(np.abs(accel[has_imu]) <= 4 * R.STANDARD_GRAVITY + 1e-3)    # the sketch's ±4 g
    assert np.all(np.abs(gyro[has_imu]) <= np.radians(2000.0) + 1e-3)         # and ±2000 °/s
    assert np.all((temp[has_imu] > -40.0) & (temp[has_imu] < 85.0))
    report = any_link.query_calibration()                  # read only: the board's EEPROM is untouched
    assert report.valid in (0, 1) and (not report.valid or report.crc == fr.cal_block_crc(
        report.cal_id, report.k, report.b))
    stats = any_link.stats
    assert stats.lost == stats.crc_errors == stats.malformed == 0 and stats.naks == 0


def test_simavr_spec_is_checked_before_anything_starts():
    with pytest.raises(InputError, match="needs a track file"):
        open_link("simavr:", read_track=Track.read)
    with pytest.raises(InputError, match="fake: boards only"):
        open_link("simavr:track.csv", speed=2.0, read_track=Track.read)
