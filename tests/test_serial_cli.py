"""``streamcal serial``: the service loop against the simulated board over a real pty."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import serial

from firmware_bridge import frames as fr
from firmware_bridge.fake_board import Faults, FakeBoard
from firmware_bridge.serial_link import SerialLink
from streamcal.calibration import Calibration
from streamcal.cli.serial import BoardSync, close_count
from streamcal.service import Notifier, SerialBlocks, Service
from streamcal.sim import simulate
from streamcal.stream import CalibrationStore, StreamingCalibrator

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def track():
    return simulate(duration_s=60.0, seed=11, motor=False).track


def board_for(track, **kw) -> FakeBoard:
    c = track.columns
    stack = lambda names: np.column_stack([c[n] for n in names])  # noqa: E731
    return FakeBoard(track.t, stack(("mx", "my", "mz")), stack(("ax", "ay", "az")),
                     stack(("gx", "gy", "gz")), c.get("temp"), **kw)


def run_host(board: FakeBoard, state_dir) -> tuple[Service, BoardSync, dict, list[str]]:
    port = serial.Serial(board.port_name, 115200, timeout=0.02)
    link = SerialLink(port, source="serial:fake", board=board)
    link.wake()
    source = SerialBlocks(link=link)
    store = CalibrationStore(state_dir)
    sync = BoardSync(source)
    log: list[str] = []
    service = Service(lambda buffer=None: StreamingCalibrator(store=store), source,
                      notifier=Notifier(environ={}), on_calibration=sync, log=log.append, name="serial")
    source_close, source.close = source.close, lambda: None
    try:
        assert service.run() == 0, log
        frames = close_count(source)
    finally:
        source_close()
    return service, sync, frames, log


@pytest.mark.slow
def test_every_frame_accounted_for_and_calibration_sent_despite_line_faults(track, tmp_path):
    faults = Faults(drop=0.01, corrupt=0.01, truncate=0.01, garbage=0.01, seed=5)
    with board_for(track, faults=faults) as board:
        service, sync, frames, log = run_host(board, tmp_path)
        assert frames["frames_received"] + frames["frames_lost"] == frames["frames_sent"] \
            == board.frames_sent
        assert frames["frames_lost"] > 0 and frames.get("crc_errors", 0) + frames.get("cobs_errors", 0) \
            + frames.get("truncated", 0) > 0
        # every calibration put in use was offered to the board; a lost ACK is retried by the link
        assert service.cal_version == sync.offered == len(sync.sent) + sync.failures >= 1
        assert len(sync.sent) >= 1 and frames["board_calibration"]["valid"]
        assert frames["board_calibration"]["cal_id"] == sync.sent[-1]


@pytest.mark.slow
def test_accepted_calibration_lands_in_eeprom_and_board_output_matches_apply(track, tmp_path):
    with board_for(track) as board:
        service, sync, frames, log = run_host(board, tmp_path)
        eeprom = bytes(board.eeprom)
    cal = service.calibrator.calibration
    assert cal is not None and Calibration.load(tmp_path / "calibration.json").model_error(cal) == 0
    assert any("board acknowledged calibration" in line for line in log)
    assert frames["frames_lost"] == 0 and frames["frames_received"] == frames["frames_sent"]
    assert eeprom[:3] == b"SC\x01"
    stored = fr.SetCalibration.unpack_body(eeprom[3:3 + fr.SetCalibration.body_size()])
    K, b = stored.matrices()
    np.testing.assert_allclose(K, cal.K, rtol=1e-6)
    np.testing.assert_allclose(b, cal.b, rtol=1e-6, atol=1e-5)
    # the board reboots with that EEPROM and streams K⁻¹(m − b) computed in float32
    with board_for(track.select(slice(0, 3000)), eeprom=eeprom) as rebooted:
        port = serial.Serial(rebooted.port_name, 115200, timeout=0.02)
        link = SerialLink(port, source="serial:fake", board=rebooted)
        link.wake()
        blocks = []
        while True:
            block = link.read_block(timeout=0.3)
            if block is not None:
                blocks.append(block)
            elif rebooted.finished.is_set():
                break
        t_cal, x_board = link.calibrated()
        link.close()
    mag = np.concatenate([blk.mag for blk in blocks])
    ok = np.all(np.isfinite(mag), axis=1)
    assert len(x_board) == ok.sum() > 500
    np.testing.assert_allclose(x_board, cal.apply(mag[ok]), rtol=2e-6, atol=2e-6)


def test_cli_over_fake_port_prints_summary(track, tmp_path):
    path = tmp_path / "track.csv"
    track.select(slice(0, 6000)).write(path)
    proc = subprocess.run([sys.executable, "-m", "streamcal", "serial", "--port", f"fake:{path}",
                           "--state-dir", str(tmp_path / "state"), "--no-socket", "--json-lines"],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    summary = json.loads(proc.stderr.strip().splitlines()[-1])
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    assert summary["link"]["frames_received"] + summary["link"]["frames_lost"] \
        == summary["link"]["frames_sent"]
    assert summary["samples"] == 6000 and len(lines) == summary["output_lines"] > 0
    x = np.array([r["direction"] for r in lines])
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=2e-6)
    assert proc.returncode == (0 if summary["cal_version"] else 1)


def test_raw_lines_sketch_is_calibrated_without_sending_back(tmp_path):
    # a MotionCal-style sketch on loop://: Raw: lines are read, nothing is sent to the board
    from streamcal.sim import simulate as sim

    tr = sim(duration_s=30.0, seed=4, motor=False, imu_rate_hz=100.0).track
    m = tr.mag[: 2500] * 10.0                       # Raw: mag counts are 0.1 µT
    lines = "".join(f"Raw:0,0,8192,0,0,0,{int(a)},{int(b_)},{int(c)}\r\n" for a, b_, c in np.rint(m))
    port = serial.serial_for_url("loop://", timeout=0.01)
    link = SerialLink(port, source="serial:loop")
    source = SerialBlocks(link=link)
    import threading
    threading.Thread(target=port.write, args=(lines.encode(),), daemon=True).start()  # loop:// is bounded
    store = CalibrationStore(tmp_path)
    sync = BoardSync(source)
    log: list[str] = []
    service = Service(lambda buffer=None: StreamingCalibrator(store=store, synchronous=True), source,
                      notifier=Notifier(environ={}), on_calibration=sync, log=log.append, max_seconds=8)
    read = source.read

    def read_until_all_seen():
        block = read()
        if service.stats.samples + (len(block) if block is not None else 0) >= len(m):
            service.request_stop("all lines read")
        return block
    source.read = read_until_all_seen
    service.run()
    assert link.mode == "raw" and service.stats.samples == len(m)
    assert sync.sent == [] and service.calibrator.calibration is not None
    assert any("Raw: lines" in line for line in log)


@pytest.mark.toolchain
@pytest.mark.slow          # ~15 s: 60 s of track through the compiled sketch in simavr (+5 s cold build)
def test_cli_runs_the_real_firmware_in_simavr(tmp_path):
    """``streamcal serial --port simavr:TRACK.csv``: the compiled sketch in simavr is the board;
    the host calibrates from its frames and the board ends up holding the stored calibration."""
    import zlib

    from firmware_bridge.simavr_board import missing_toolchain

    missing = missing_toolchain()
    if missing:
        message = "simavr toolchain missing: " + ", ".join(missing) + " (HARDWARE.md §7)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    run = simulate(duration_s=60.0, seed=11, motor=False)
    path = tmp_path / "track.csv"
    run.track.write(path)
    state = tmp_path / "state"
    proc = subprocess.run([sys.executable, "-m", "streamcal", "serial", "--port", f"simavr:{path}",
                           "--state-dir", str(state), "--no-socket", "--sync-fits", "--max-seconds", "120"],
                          capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["stop_reason"] == "end of replay"
    link = summary["link"]
    assert link["frames_lost"] == 0 and summary["source"]["crc_errors"] == summary["source"]["cobs_errors"] == 0
    # the sketch samples every 5 ms: the whole 60 s track arrived
    assert summary["samples"] >= 0.97 * 60.0 * 200
    # the calibration the host stored is the track's truth, and it is the one the board holds
    cal = Calibration.load(state / "calibration.json")
    np.testing.assert_allclose(cal.b, run.truth.b, atol=0.5)
    np.testing.assert_allclose(np.diag(cal.K), np.diag(run.truth.K), rtol=0.01)
    assert summary["sent_to_board"] == summary["cal_version"] >= 1
    cal_id = zlib.crc32(np.concatenate([cal.K.ravel(), cal.b]).astype("<f8").tobytes()) & 0xFFFF
    assert link["board_calibration"] == {"valid": True, "cal_id": cal_id}
    assert f"board acknowledged calibration id 0x{cal_id:04X}" in proc.stderr


def test_cli_draws_the_coverage_map_on_stderr_unless_json_lines(tmp_path, capsys):
    import signal

    from streamcal.cli import main

    path = tmp_path / "track.csv"
    simulate(duration_s=30.0, seed=3, motor=False).track.write(path)
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    results = []
    try:
        for extra in ([], ["--json-lines"]):
            code = main(["serial", "--port", f"fake:{path}", "--state-dir", str(tmp_path / f"s{len(extra)}"),
                         "--no-socket", "--sync-fits", *extra])
            results.append((code, *capsys.readouterr()))
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
    for (code, out, err), json_lines in zip(results, (False, True)):
        assert code in (0, 1), err
        milestones = err.count(" coverage: coverage ")
        assert milestones >= 2
        assert err.count("% of the sphere (") == err.count("█ seen  · not yet") == (0 if json_lines else milestones)
        assert "█ seen" not in out
        summary = json.loads((err if json_lines else out).strip().splitlines()[-1])
        assert summary["events"]["coverage"] == milestones
