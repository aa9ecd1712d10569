"""``streamcal replay --realtime --http``: the live page fed from the replay loop."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pytest

from streamcal.sim.scenario import simulate
from tests.test_live_page import REPO, sse_events


@pytest.mark.slow
def test_replay_realtime_serves_the_page(tmp_path):
    track = tmp_path / "short.csv"
    simulate(25, seed=5, motor=False).track.write(track)
    err = open(tmp_path / "stderr.txt", "w+")
    proc = subprocess.Popen([sys.executable, "-m", "streamcal", "replay", str(track), "--realtime",
                             "--json", "--http", "127.0.0.1:0", "--lat", "43", "--lon", "21",
                             "--date", "2025-07-01"],
                            stdout=subprocess.DEVNULL, stderr=err, cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        url = None
        deadline = time.monotonic() + 30
        while url is None and time.monotonic() < deadline and proc.poll() is None:
            err.seek(0)
            found = re.search(r"live page at (http://[\d.]+:\d+/)", err.read())
            url = found.group(1) if found else None
            time.sleep(0.1)
        assert url, (err.seek(0), err.read()[-2000:])
        events = sse_events(url, seconds=4.0)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert len(events) >= 6, [e["uptime_s"] for e in events]
    cov = [e["coverage"] for e in events if e["coverage"] is not None]   # null: not framed yet
    assert len(cov) >= 4 and cov[-1] > cov[0], [e["coverage"] for e in events]
    last = events[-1]
    assert last["device"]["state"] == "replaying" and last["device"]["samples_per_s"] > 0
    assert last["reference"]["source"] == "WMM2025"
    # the track's pace: 300 rows per track second (100 Hz mag + 200 Hz IMU rows); a replay at
    # full speed would show tens of thousands
    assert 150 < last["device"]["samples_per_s"] < 450, last["device"]


def test_replay_http_needs_realtime(tmp_path):
    track = tmp_path / "short.csv"
    simulate(5, seed=5, motor=False).track.write(track)
    out = subprocess.run([sys.executable, "-m", "streamcal", "replay", str(track), "--http",
                          "127.0.0.1:0"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode != 0
    assert "--http needs --realtime" in out.stderr
