"""``streamcal serial`` shows the board's own calibration beside the host's, and which is in force
and why: the formatting on decoded SELF_CAL frames (the fake board does not calibrate itself),
and the whole command against the compiled sketch in simavr (CI)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge import frames as fr
from firmware_bridge.selfcal_frames import CalOrigin, SelfCal, SelfCalEvent, SelfCalReason
from streamcal.calibration import Calibration
from streamcal.cli._selfcal import WHY_HOST, board_self_cal, format_board_self_cal

REPO = Path(__file__).resolve().parent.parent


def _frame(event, reason, origin, in_force_id, R=48.0, b=(10.0, -20.0, 5.0), cal_id=0xB001, loss_old=math.nan):
    cand = fr.SetCalibration.from_kb(np.diag([R] * 3), list(b), cal_id=cal_id)
    msg = SelfCal(event=int(event), reason=int(reason), origin=int(origin), in_force_id=in_force_id, cells=57,
                  n_fit=5000, n_check=2600 if event != SelfCalEvent.FITTED else 0, fit_cost=0.0004,
                  loss_new=0.0015, loss_old=loss_old, fit_cycles=400000, sample_cycles=13000,
                  cal_id=cand.cal_id, k=cand.k, b=cand.b, crc=cand.crc)
    return fr.FrameDecoder().feed(fr.encode(msg, 1))[0].msg      # as the link decodes it


def test_board_fit_accepted_is_in_force_with_its_reason_and_distance_to_host():
    frames = [_frame(SelfCalEvent.FITTED, SelfCalReason.NONE, CalOrigin.NONE, 0),
              _frame(SelfCalEvent.ACCEPTED, SelfCalReason.NO_CAL_IN_FORCE, CalOrigin.BOARD, 0xB001)]
    host = Calibration(K=np.diag([48.0, 48.0, 48.0]) * 1.01, b=np.array([10.0, -20.0, 5.0]))
    info = board_self_cal(frames, host, board_cal_id=0xB001)
    assert info["events"] == {"fitted": 1, "accepted": 1}
    assert info["in_force"]["origin"] == "board" and info["in_force"]["cal_id"] == 0xB001
    assert "no calibration was in force" in info["in_force"]["why"]
    K, b = frames[0].matrices()
    assert info["board_fit_vs_host"] == pytest.approx(Calibration(K=K, b=b).model_error(host))
    assert 0.005 < info["board_fit_vs_host"] < 0.02
    text = format_board_self_cal(info)
    assert "in force on the board: board 0xB001" in text and "(relative model error, eq. 40 of the paper)" in text and "R 48.00 uT" in text
    json.dumps(info)                                  # JSON-ready (it goes into the summary line)


def test_host_calibration_sent_after_the_last_board_event_is_reported_in_force():
    frames = [_frame(SelfCalEvent.FITTED, SelfCalReason.NONE, CalOrigin.NONE, 0),
              _frame(SelfCalEvent.ACCEPTED, SelfCalReason.NO_CAL_IN_FORCE, CalOrigin.BOARD, 0xB001)]
    info = board_self_cal(frames, None, board_cal_id=0x0042, sent_ids=[0x0041, 0x0042])
    assert info["in_force"] == {"origin": "host", "cal_id": 0x0042, "why": WHY_HOST}
    assert info["board_fit_vs_host"] is None
    assert "the host has no calibration yet" in format_board_self_cal(info)


def test_rejected_candidate_leaves_the_host_calibration_and_says_why():
    frames = [_frame(SelfCalEvent.FITTED, SelfCalReason.NONE, CalOrigin.HOST, 0x0042),
              _frame(SelfCalEvent.REJECTED, SelfCalReason.NOT_BETTER, CalOrigin.HOST, 0x0042, loss_old=0.0016)]
    info = board_self_cal(frames, None, board_cal_id=0x0042, sent_ids=[0x0042])
    assert info["in_force"]["origin"] == "host"
    assert "does not fit the held-out samples better" in info["last"]
    assert board_self_cal([], None) is None


@pytest.mark.toolchain
@pytest.mark.slow
def test_serial_cli_on_the_sketch_in_simavr_shows_the_board_calibration(tmp_path):
    from firmware_bridge.simavr_board import missing_toolchain
    missing = missing_toolchain()
    if missing:
        if os.environ.get("CI"):
            pytest.fail("simavr toolchain missing: " + ", ".join(missing))
        pytest.skip("simavr toolchain missing: " + ", ".join(missing))
    from streamcal.inputs.track import Track
    track = Track.read(REPO / "streamcal" / "data" / "demo_track.csv.gz")
    keep = track.t < track.t[0] + 60.0          # the first window fills at ~51 s
    c = track.columns
    triple = lambda names: np.column_stack([c[n][keep] for n in names])  # noqa: E731
    excerpt = Track.from_arrays(track.t[keep], mag=triple(("mx", "my", "mz")), accel=triple(("ax", "ay", "az")),
                                gyro=triple(("gx", "gy", "gz")), temp=c["temp"][keep])
    path = tmp_path / "excerpt.csv"
    excerpt.write(path)
    res = subprocess.run([sys.executable, "-m", "streamcal", "serial", "--port", f"simavr:{path}",
                          "--state-dir", str(tmp_path / "state")], capture_output=True, text=True,
                         timeout=900, cwd=REPO)
    assert res.returncode == 0, res.stderr[-3000:]
    print(res.stdout[-3000:])
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    board = summary["board_self_cal"]
    assert board["events"].get("fitted", 0) >= 1 and board["fit"]["n_fit"] > 1000
    assert board["in_force"]["origin"] in ("host", "board") and board["in_force"]["why"]
    assert "in force on the board:" in res.stdout and "latest board fit 0xB" in res.stdout
