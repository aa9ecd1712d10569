"""The real streamcal_bridge firmware in the loop: the compiled Uno sketch runs in simavr
(tools/simavr_harness) against register-level MPU-9250/AK8963 slaves replaying a track, and the
host talks to it through SerialLink over the harness's pty."""
from __future__ import annotations

import os
import struct
import time

import numpy as np
import pytest

from firmware_bridge import frames as fr
from firmware_bridge import registers as R
from firmware_bridge.fake_mpu9250 import FakeMPU9250Bus
from firmware_bridge.simavr_board import (F_CPU_HZ, REPLAY_MAGIC, SimavrBoard, missing_toolchain,
                                          replay_bytes)
from streamcal.calibration import Calibration
from streamcal.inputs.track import Track

DEMO = os.path.join(os.path.dirname(__file__), "..", "streamcal", "data", "demo_track.csv.gz")
ASA = (0xB0, 0xB2, 0xA5)          # fuse-ROM bytes of the simulated AK8963 (chip x, y, z)
ACCEL_FS, GYRO_FS = 1, 3          # the sketch sets ±4 g and ±2000 °/s
READ_WINDOW_S = 3e-3              # a poll's I²C reads start within this after its micros() stamp
CAL = Calibration(K=np.array([[41.0, 1.5, -2.0], [0.0, 44.0, 0.75], [0.0, 0.0, 52.0]]),
                  b=np.array([12.5, -20.25, 6.0]), model=("hard_iron", "soft_iron"))


def _need_toolchain():
    missing = missing_toolchain()
    if missing:
        message = ("simavr toolchain missing: " + ", ".join(missing) + "; install: apt-get install -y "
                   "--no-install-recommends simavr libsimavr-dev libsimavrparts1 libelf-dev pkg-config "
                   "arduino-builder arduino-core-avr gcc-avr avr-libc binutils-avr g++ make")
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)


def _excerpt(seconds: float) -> Track:
    track = Track.read(DEMO)
    c, keep = track.columns, track.t < track.t[0] + seconds
    triple = lambda names: np.column_stack([c[n][keep] for n in names])  # noqa: E731
    return Track.from_arrays(track.t[keep], mag=triple(("mx", "my", "mz")), accel=triple(("ax", "ay", "az")),
                             gyro=triple(("gx", "gy", "gz")), temp=c["temp"][keep])


def _rows(track: Track, names):
    v = np.column_stack([track.columns[n] for n in names])
    ok = np.all(np.isfinite(v), axis=1)
    return track.t[ok], v[ok]


def _tolerance(rows, chip_scale, board_scale):
    """Per-element bound on |received - track| (same shape as ``rows``): half an LSB of the chip
    model's encoding plus the difference between its scale and the one the board announces
    (float32 rounding only: the sketch and the chip model use the same datasheet scales)."""
    chip_scale, board_scale = np.asarray(chip_scale, float), np.asarray(board_scale, float)
    return 0.5 * chip_scale + np.abs(rows) * np.abs(board_scale / chip_scale - 1) + 1e-9


def _match_rows(tau, got, t_rows, want, tol):
    """Index of the track row each received sample came from: the row current at some instant in
    [tau, tau + READ_WINDOW_S] whose values agree within ``tol`` (per element); -1 if none."""
    lo = np.searchsorted(t_rows, tau, side="right") - 1
    hi = np.searchsorted(t_rows, tau + READ_WINDOW_S, side="right") - 1
    out = np.full(len(tau), -1)
    for d in range(int(np.max(hi - lo, initial=0)) + 1):    # ≤ 2 candidates at 200 Hz rows
        k = np.clip(lo + d, 0, len(t_rows) - 1)
        hit = (out < 0) & (lo + d >= 0) & (lo + d <= hi) & np.all(np.abs(got - want[k]) <= tol[k], axis=1)
        out[hit] = k[hit]
    return out


def test_replay_file_holds_the_fake_chips_counts():
    """Pure Python (no toolchain): the harness's input carries the fake chip's own encoding."""
    track = _excerpt(2.0)
    blob = replay_bytes(track, lead_s=0.25, asa=ASA)
    assert blob[:8] == REPLAY_MAGIC
    n_acc, n_gyr, n_tmp, n_mag = struct.unpack_from("<4I", blob, 8)
    whoami, ak_wia, has_mag = blob[24:27]
    assert (whoami, ak_wia, has_mag, tuple(blob[27:30])) == (0x71, 0x48, 1, ASA)
    off = 32
    acc_cyc = np.frombuffer(blob, "<i8", n_acc, off); off += 8 * n_acc
    acc = np.frombuffer(blob, "<i2", n_acc * 12, off).reshape(n_acc, 4, 3); off += 24 * n_acc
    off += (8 + 24) * n_gyr + (8 + 2) * n_tmp
    mag_cyc = np.frombuffer(blob, "<i8", n_mag, off); off += 8 * n_mag
    mag = np.frombuffer(blob, "<i2", n_mag * 6, off).reshape(n_mag, 2, 3); off += 12 * n_mag
    assert len(blob) == off + 2 * n_mag
    t_acc, a = _rows(track, ("ax", "ay", "az"))
    t_mag, m = _rows(track, ("mx", "my", "mz"))
    assert (n_acc, n_mag) == (len(t_acc), len(t_mag))
    np.testing.assert_array_equal(acc_cyc, np.rint((t_acc - track.t[0] + 0.25) * F_CPU_HZ))
    np.testing.assert_array_equal(mag_cyc, np.rint((t_mag - track.t[0] + 0.25) * F_CPU_HZ))
    for fs in range(4):   # decoding with the driver's scales gives the track back within ½ LSB
        np.testing.assert_allclose(acc[:, fs] * R.accel_scale(fs), a, atol=0.5 * R.accel_scale(fs) + 1e-12)
    for bits, j in ((14, 0), (16, 1)):
        scale = R.mag_scale(bits) * R.asa_factor(ASA)            # µT per count, chip axes
        body = (mag[:, j] * scale) @ R.AK_TO_BODY.T
        np.testing.assert_allclose(body, m, atol=0.5 * scale.max() + 1e-9)
    # and it is the very encoding the fake serves to the Python driver
    bus = FakeMPU9250Bus.from_track(track, asa=ASA)
    np.testing.assert_array_equal(acc[:, ACCEL_FS], bus.encoded_rows(accel_fs=ACCEL_FS).accel)


def _mag_section(blob):
    """(header ASA bytes, mag counts (Nm, [14, 16], 3)) of a replay file."""
    n_acc, n_gyr, n_tmp, n_mag = struct.unpack_from("<4I", blob, 8)
    off = 32 + (8 + 24) * (n_acc + n_gyr) + (8 + 2) * n_tmp + 8 * n_mag
    return tuple(blob[27:30]), np.frombuffer(blob, "<i2", n_mag * 6, off).reshape(n_mag, 2, 3)


def test_replay_file_of_a_raw_count_log_keeps_its_counts_and_its_asa(real_tracks_dir, tmp_path):
    """A raw AK8963 log is served unchanged, so the fuse ROM must hold the ASA its metadata
    records (here the default 128 when it records none; then a stated one), not the µT default."""
    src = Track.read(real_tracks_dir / "tiva_mpu9250_mag_02.csv")
    asa_stated, counts = _mag_section(replay_bytes(src))
    assert asa_stated == (128, 128, 128)
    t_mag, m = _rows(src, ("mx", "my", "mz"))
    np.testing.assert_array_equal(counts[:, 1, :], m)          # 16-bit output: the log's own counts
    lines = (real_tracks_dir / "tiva_mpu9250_mag_02.csv").read_text().splitlines()
    path = tmp_path / "with_asa.csv"
    path.write_text("\n".join(lines[:1] + ["# asa: 170,190,160"] + lines[1:400]) + "\n")
    asa_stated, counts = _mag_section(replay_bytes(Track.read(path)))
    assert asa_stated == (170, 190, 160)
    np.testing.assert_array_equal(counts[:, 1, :], m[:len(counts)])
    assert _mag_section(replay_bytes(_excerpt(1.0)))[0] == ASA  # a µT track: the typical default


@pytest.mark.toolchain
@pytest.mark.slow          # ~7-9 s with cached builds (20 s of track at ~3-4x real time), +5 s cold
def test_firmware_streams_track_accounts_for_every_frame_and_applies_calibration():
    _need_toolchain()
    track = _excerpt(20.0)
    wall0 = time.monotonic()
    with SimavrBoard(track, asa=ASA) as board:
        link = board.open_link()
        cal_id = link.send_calibration(CAL)                       # → ACK (LinkError otherwise)
        t_end = track.t[-1]
        blocks = []
        stream0 = time.monotonic()
        for block in link.blocks(idle_timeout=10.0):
            blocks.append(block)
            if board.track_time(block.t[-1]) > t_end + 0.05:      # every mag row has been served
                break
        stream_wall = time.monotonic() - stream0
        link.stop()                                               # the board goes quiet after its ACK
        report = link.query_calibration()
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:                        # drain what is still in flight
            link.pump()
        blocks += list(iter(lambda: link.read_block(timeout=0.05), None))
        t_cal, x_board = link.calibrated()
        stats = link.stats
        last_seq_next = link.sequence.expected
        link.close()                                              # closes the board too (SIGTERM)
    hs = board.stats
    wall = time.monotonic() - wall0
    hello = link.hello
    t = np.concatenate([b.t for b in blocks])
    mag, acc, gyr = (np.concatenate([getattr(b, k) for b in blocks]) for k in ("mag", "accel", "gyro"))
    tau = board.track_time(t)
    n_stream = int(np.sum(tau <= t_end + 0.05))
    print(f"\nsimavr firmware-in-loop: {len(t)} samples, {hs['sim_s']:.2f} s simulated in {hs['wall_s']:.2f} s "
          f"harness wall ({hs['sim_s'] / hs['wall_s']:.2f}x real time); track streaming {n_stream / stream_wall:.0f} "
          f"samples/s wall; whole test {wall:.1f} s; harness {hs}")

    # identity and scales as the sketch announces them
    assert (hello.whoami, hello.ak_wia) == (0x71, R.AK8963_WIA)
    assert hello.flags & fr.HelloFlags.MAG_PRESENT
    assert hs["state"] == "stopped" and board.returncode == 0 and hs["violations"] == 0

    # every frame accounted for: the harness counted frame delimiters on the UART
    assert stats.lost == 0 and stats.crc_errors == stats.cobs_errors == stats.truncated == 0
    assert stats.malformed == stats.garbage_bytes == stats.dropped == 0 and hs["out_overflow"] == 0
    assert stats.frames + stats.lost == last_seq_next == hs["uart_tx_frames"]

    # accel and gyro: each sample is the track row current when the sketch read it, within ½ LSB
    t_a, a_rows = _rows(track, ("ax", "ay", "az"))
    t_g, g_rows = _rows(track, ("gx", "gy", "gz"))
    live = (tau >= max(t_a[0], t_g[0])) & (tau <= t_end)
    assert np.all(np.isfinite(acc[live])) and np.all(np.isfinite(gyr[live]))
    before = tau + READ_WINDOW_S < min(t_a[0], t_g[0])       # read before the track's first row
    assert before.sum() > 0 and np.all(acc[before] == 0) and np.all(gyr[before] == 0)
    k_acc = _match_rows(tau[live], acc[live], t_a, a_rows,
                        _tolerance(a_rows, R.accel_scale(ACCEL_FS), hello.accel_scale))
    k_gyr = _match_rows(tau[live], gyr[live], t_g, g_rows,
                        _tolerance(g_rows, R.gyro_scale(GYRO_FS), hello.gyro_scale))
    assert np.all(k_acc >= 0), f"{np.sum(k_acc < 0)} accel samples match no track row"
    assert np.all(k_gyr >= 0), f"{np.sum(k_gyr < 0)} gyro samples match no track row"

    # magnetometer: each valid sample is one track row, in order; rows never received are exactly
    # the ones the harness's AK8963 overwrote before the sketch read them (DOR)
    t_m, m_rows = _rows(track, ("mx", "my", "mz"))
    s_fake = R.mag_scale(16) * np.asarray(R.asa_factor(ASA)) @ np.abs(R.AK_TO_BODY)   # body axes
    s_sketch = np.array(hello.mag_scale)
    # the sketch announces the datasheet's 4912/32760 µT/LSB × ASA, as the chip model encodes it:
    # they differ by float32 rounding only (a few ulp), so the bound is ½ LSB
    np.testing.assert_allclose(s_sketch, s_fake, rtol=3e-7)
    tol = _tolerance(m_rows, s_fake, s_sketch)
    valid = np.all(np.isfinite(mag), axis=1)
    k_mag = _match_rows(tau[valid], mag[valid], t_m, m_rows, tol)
    assert np.all(k_mag >= 0), f"{np.sum(k_mag < 0)} mag samples match no track row"
    # a row equal to the row before it (this track has one such pair, at 9.84 s) matches either:
    # of two samples given the same row, the later one is the later row when that row is equal
    for i in np.flatnonzero(np.diff(k_mag) == 0) + 1:
        if k_mag[i] + 1 < len(m_rows) and np.array_equal(m_rows[k_mag[i] + 1], m_rows[k_mag[i]]):
            k_mag[i] += 1
    assert np.all(np.diff(k_mag) > 0)
    never_received = len(m_rows) - len(k_mag)
    assert hs["mag_next"] == hs["mag_rows"] == len(m_rows)
    assert never_received == hs["skipped"] + hs["hofl"], (never_received, hs)
    # polling at 5 ms, twice the AK8963 rate, the sketch reads every magnetometer sample: none
    # overwritten before it was read (DOR), none lost on the way (this track has no overflow)
    assert hello.period_us == 5000 and np.median(np.diff(t)) == pytest.approx(5e-3, abs=1e-5)
    imu_share = len(t) / ((t[-1] - t[0]) / 5e-3 + 1)      # polls sent / 5 ms slots
    print(f"5 ms slots with a SAMPLE frame: {100 * imu_share:.1f} %; serial "
          f"{hs['uart_tx_bytes'] / hs['sim_s']:.0f} B/s of 11520")
    assert imu_share > 0.97
    assert hs["skipped"] == hs["dor_reported"] == stats.mag_overflows == 0
    assert never_received == 0 and np.all(np.diff(k_mag) == 1)
    assert stats.mag_overflows == hs["hofl"]

    # the board's calibrated output is Calibration.apply of the same µT values, in float32
    assert report.valid == 1 and report.cal_id == cal_id and report.crc == fr.cal_block_crc(
        cal_id, report.k, report.b)
    K, b = fr.SetCalibration(cal_id=report.cal_id, k=report.k, b=report.b, crc=report.crc).matrices()
    np.testing.assert_allclose(K, CAL.K, rtol=1e-7)
    np.testing.assert_allclose(b, CAL.b, rtol=1e-7)
    rows = valid & (t >= t_cal[0])
    assert len(t_cal) == rows.sum() > 0.95 * len(m_rows) - hs["skipped"]
    np.testing.assert_array_equal(t_cal, t[rows])
    np.testing.assert_allclose(x_board, CAL.apply(mag[rows]), rtol=2e-6, atol=2e-6)

    # sphere sums on the board cover the samples it read
    assert link.sphere_sums is not None and link.sphere_sums.n > 0


EE_SLOTS = (0, 64)          # EEPROM layout 2: two 46-byte slots (streamcal_bridge.ino)


def ee_slot(image: bytes, i: int):
    """(valid, origin, seq, SetCalibration) of EEPROM slot ``i``: layout 2, slot CRC, block CRC."""
    raw = image[EE_SLOTS[i]:EE_SLOTS[i] + 46]
    block = fr.SetCalibration.unpack_body(raw[4:44])
    valid = raw[0] == 2 and fr.crc16(raw[:44]) == struct.unpack("<H", raw[44:])[0] and block.crc_ok()
    return valid, raw[1], struct.unpack("<H", raw[2:4])[0], block


@pytest.mark.toolchain
def test_calibration_survives_reboot_in_simulated_eeprom(tmp_path):
    _need_toolchain()
    track = _excerpt(1.0)
    eeprom = tmp_path / "eeprom.bin"
    with SimavrBoard(track, asa=ASA, eeprom=eeprom) as board:
        link = board.open_link()
        assert link.request_info().flags & fr.HelloFlags.CAL_LOADED == 0
        cal_id = link.send_calibration(CAL, cal_id=77)
        link.close()
    assert board.returncode == 0 and eeprom.stat().st_size == 1024
    image = eeprom.read_bytes()
    valid, origin, seq, stored = ee_slot(image, 0)
    assert valid and origin == 1 and seq == 1 and not ee_slot(image, 1)[0]
    assert stored.cal_id == cal_id == 77 and stored.crc_ok()
    with SimavrBoard(track, asa=ASA, eeprom=eeprom) as rebooted:
        link = rebooted.open_link()
        assert link.request_info().flags & fr.HelloFlags.CAL_LOADED
        report = link.query_calibration()
        assert report.valid == 1 and (report.cal_id, report.k, report.b) == (77, stored.k, stored.b)
        link.clear_calibration()
        assert link.query_calibration().valid == 0
        link.close()
    image = eeprom.read_bytes()
    assert not ee_slot(image, 0)[0] and not ee_slot(image, 1)[0]     # CLEAR_CAL invalidated both


@pytest.mark.slow
@pytest.mark.toolchain
def test_reset_in_the_middle_of_an_eeprom_write_keeps_the_previous_calibration(tmp_path):
    """SET_CAL A, then SET_CAL B with the AVR reset right after its k-th EEPROM byte write: on
    reboot A is in force for every k before the last byte, B once the write is complete."""
    _need_toolchain()
    track = _excerpt(0.5)
    first = tmp_path / "a.bin"
    cal_b = CAL.replace(b=CAL.b + np.array([3.0, -2.0, 1.0]))
    with SimavrBoard(track, asa=ASA, eeprom=first) as board:
        link = board.open_link()
        link.send_calibration(CAL, cal_id=0xA)
        link.close()
    dry = tmp_path / "dry.bin"
    dry.write_bytes(first.read_bytes())
    with SimavrBoard(track, asa=ASA, eeprom=dry) as board:
        link = board.open_link()
        link.send_calibration(cal_b, cal_id=0xB)
        link.close()
    writes_b = board.stats["eeprom_writes"]
    assert 10 < writes_b <= 46                   # EEPROM.update writes only the bytes that change
    for k in sorted({1, writes_b // 2, writes_b - 1, writes_b}):
        image = tmp_path / f"k{k}.bin"
        image.write_bytes(first.read_bytes())
        with SimavrBoard(track, asa=ASA, eeprom=image, reset_at_eeprom_write=k) as board:
            link = board.open_link()
            try:
                link.send_calibration(cal_b, cal_id=0xB, retries=0, timeout=1.0)
            except Exception:
                pass                             # the board reset before it could answer
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                link.pump()
            link.request_info()                   # the boot HELLO may be glued to the cut frame
            report = link.query_calibration()
            link.close()
        assert board.stats["resets"] == 1 and board.stats["eeprom_writes"] >= k
        changed = image.read_bytes() != first.read_bytes()
        assert changed                            # the write had begun
        expected = 0xB if k == writes_b else 0xA
        assert report.valid == 1 and report.cal_id == expected, (k, writes_b, report)
