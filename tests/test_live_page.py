"""The live page server (``--http``): SSE events, limits, bad requests, slow clients, token."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from streamcal.service.http_page import PEER_CHECK_S, LivePage, parse_http

REPO = Path(__file__).resolve().parent.parent
TRACK = REPO / "streamcal" / "data" / "demo_track.csv.gz"


def start_daemon(tmp_path, *extra, speed="3", seconds="60", device=None):
    """``streamcal daemon --bus fake:TRACK --speed SPEED --http 127.0.0.1:0`` (``device``: other
    leading arguments, e.g. ``serial --port fake:TRACK``); returns (process, base URL) once the
    process has said where its page listens (it listens before it says so). Its stderr goes on
    being collected into ``process.stderr_lines`` (and ``tmp_path/stderr.txt``)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    device = device or ["daemon", "--bus", f"fake:{TRACK}", "--speed", speed]
    proc = subprocess.Popen([sys.executable, "-m", "streamcal", *device, "--no-socket", "--state-dir", str(tmp_path / "s"),
                             "--max-seconds", seconds, "--http", "127.0.0.1:0", *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=REPO)
    lines = StderrLines(proc, tmp_path / "stderr.txt")
    found = lines.wait_for(r"live page at (http://[\d.]+:\d+/)", 60)
    if found is None:
        proc.kill()
        pytest.fail(f"daemon did not print the live page address: {lines.text()[-2000:]}")
    return proc, found.group(1)


class StderrLines:
    """A process's stderr, read line by line on a thread (the pipe never fills) and copied to
    ``path``; :meth:`wait_for` blocks until a line matches, without polling."""

    def __init__(self, proc, path):
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._done = False
        self._copy = open(path, "w")
        proc.stderr_lines = self
        threading.Thread(target=self._read, args=(proc.stderr,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            self._copy.write(line)
            self._copy.flush()
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._done = True
            self._changed.notify_all()

    def text(self) -> str:
        with self._changed:
            return "".join(self.lines)

    def wait_for(self, pattern: str, timeout: float):
        """The first match of ``pattern`` in a line, or None at end of stream or ``timeout``."""
        regex = re.compile(pattern)
        seen = 0
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.lines[seen:]:
                    if (found := regex.search(line)):
                        return found
                seen = len(self.lines)
                left = deadline - time.monotonic()
                if self._done or left <= 0:
                    return None
                self._changed.wait(left)


def _addr(url):
    host, port = url.split("//")[1].rstrip("/").split(":")
    return host, int(port)


def request(url, raw: bytes, timeout=5.0) -> bytes:
    with socket.create_connection(_addr(url), timeout=timeout) as s:
        s.sendall(raw)
        out = b""
        while True:
            try:
                chunk = s.recv(65536)
            except socket.timeout:
                break
            if not chunk:
                break
            out += chunk
        return out


def sse_events(url, path="/events", seconds=3.0, until=None) -> list[dict]:
    """JSON of the ``data:`` lines received on ``path`` during ``seconds``, or up to the first
    for which ``until(event)`` holds (then within ``seconds``: else the test fails)."""
    buf = b""
    end = time.monotonic() + seconds
    with socket.create_connection(_addr(url), timeout=1.0) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        while time.monotonic() < end:
            try:
                chunk = s.recv(65536)
            except socket.timeout:
                continue
            if not chunk:
                break
            buf += chunk
            if until is not None and any(until(e) for e in _data_lines(buf.partition(b"\r\n\r\n")[2])):
                break
    head, _, body = buf.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.0 200"), head[:200]
    assert b"Content-Type: text/event-stream" in head
    events = _data_lines(body)
    if until is not None:
        hit = next((i for i, e in enumerate(events) if until(e)), None)
        assert hit is not None, f"no event met the condition in {seconds} s: {events[-1:]}"
        events = events[:hit + 1]
    return events


def _data_lines(body: bytes) -> list[dict]:
    """The complete ``data:`` events of an SSE body (a line still arriving is left out)."""
    done = body[:body.rfind(b"\n\n") + 2] if b"\n\n" in body else b""
    return [json.loads(line[6:]) for line in done.split(b"\n") if line.startswith(b"data: ")]


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    proc, url = start_daemon(tmp_path_factory.mktemp("live"))
    yield proc, url
    proc.terminate()
    proc.wait(timeout=30)


@pytest.mark.slow
def test_sse_delivers_json_with_coverage_growing(daemon):
    proc, url = daemon
    events = sse_events(url, seconds=4.0)
    up = [e["uptime_s"] for e in events]
    gaps = sorted(b - a for a, b in zip(up, up[1:]))
    assert len(events) >= 6, up
    assert gaps[len(gaps) // 2] <= 0.5, up           # at least twice a second
    assert gaps[0] >= 0.25 - 0.02, up                # captures at most every 0.25 s
    # not measured (null, with the reason as the hint) until the running sphere frames the
    # directions; from then on a number that grows
    cov = [e["coverage"] for e in events]
    first = next(i for i, c in enumerate(cov) if c is not None)
    assert all(e["hint"].startswith("coverage not measured") and e["gap"] is None
               and "1" not in e["occupied"] for e in events[:first]), events[:first]
    cov = cov[first:]
    assert None not in cov and len(cov) >= 4, cov
    assert all(b >= a - 0.05 for a, b in zip(cov, cov[1:])), cov
    assert cov[-1] > cov[0], cov
    last = events[-1]
    assert len(last["occupied"]) == sum(last["cells"]["counts"])
    assert abs(last["occupied"].count("1") / len(last["occupied"]) - last["coverage"]) < 1e-3
    assert last["device"]["samples_per_s"] > 0
    assert last["magnitude"]["t"] and max(last["magnitude"]["t"]) <= 0
    assert 0 <= last["gap"]["deg"] <= 180 and last["hint"]


@pytest.mark.slow
def test_hundred_connections_excess_get_503_and_daemon_runs(daemon):
    proc, url = daemon
    time.sleep(5 * PEER_CHECK_S)       # streams of earlier tests: closed, their slots freed by now
    socks = []
    for _ in range(100):
        s = socket.create_connection(_addr(url), timeout=5.0)
        s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        socks.append(s)
    status = []
    for s in socks:
        try:
            status.append(s.recv(64).split(b" ")[1])
        except (socket.timeout, IndexError, OSError):
            status.append(b"none")
    ok, busy = status.count(b"200"), status.count(b"503")
    assert ok == 16, status
    assert busy == 84, status
    for s in socks:
        s.close()
    time.sleep(0.5)
    assert proc.poll() is None
    seq0 = json.loads(request(url, b"GET /state.json HTTP/1.0\r\n\r\n").partition(b"\r\n\r\n")[2])["seq"]
    time.sleep(1.0)
    seq1 = json.loads(request(url, b"GET /state.json HTTP/1.0\r\n\r\n").partition(b"\r\n\r\n")[2])["seq"]
    assert seq1 > seq0
    assert sse_events(url, seconds=1.5)             # a stream is free again


def test_busy_message_is_clear(daemon):
    proc, url = daemon
    time.sleep(5 * PEER_CHECK_S)       # streams of earlier tests: closed, their slots freed by now
    socks = [socket.create_connection(_addr(url), timeout=5.0) for _ in range(17)]
    try:
        for s in socks:
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        replies = [s.recv(4096) for s in socks]
        replies = [r + _rest(s) if r.startswith(b"HTTP/1.0 503") else r
                   for r, s in zip(replies, socks)]
        refused = [r for r in replies if r.startswith(b"HTTP/1.0 503")]
        assert len(refused) == 1
        assert b"16 live views are open already" in refused[0]
    finally:
        for s in socks:
            s.close()


def _rest(s) -> bytes:
    out = b""
    while chunk := s.recv(4096):
        out += chunk
    return out


@pytest.mark.parametrize("raw", [b"\x00\xff\xfe garbage\r\n\r\n", b"GET\r\n\r\n",
                                 b"GET / HTTP/9.Z\r\n\r\n", b"\x16\x03\x01\x02\x00\x01\x00\r\n\r\n"])
def test_garbage_gets_400(daemon, raw):
    proc, url = daemon
    reply = request(url, raw)
    assert reply.startswith(b"HTTP/1.0 400"), reply[:100]
    assert proc.poll() is None


def test_unknown_path_404_and_page_served(daemon):
    proc, url = daemon
    assert request(url, b"GET /etc/passwd HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 404")
    page = request(url, b"GET / HTTP/1.0\r\n\r\n")
    assert page.startswith(b"HTTP/1.0 200")
    assert b'<span id="coverage">' in page and b"EventSource" in page
    assert b"http://" not in page.partition(b"\r\n\r\n")[2].split(b"<script id=\"initial\"")[0]


class _FastState:
    """A state producing a large snapshot every 5 ms (fills a non-reading client's socket)."""

    def __init__(self):
        self.seq = 0

    def wait(self, seq, timeout):
        time.sleep(0.005)
        self.seq += 1
        return self.seq

    def build(self):
        return {"seq": self.seq, "coverage": 0.5, "pad": "x" * 200_000}


def test_client_that_never_reads_is_dropped():
    page = LivePage(_FastState(), "127.0.0.1", 0, timeout_s=30.0).start()
    try:
        url = page.url
        stuck = socket.create_connection(_addr(url))
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        deadline = time.monotonic() + 20
        while page.stats["dropped_slow"] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert page.stats["dropped_slow"] == 1
        deadline = time.monotonic() + 5
        while page.n_clients and time.monotonic() < deadline:
            time.sleep(0.05)
        assert page.n_clients == 0
        before = page.stats["events"]
        time.sleep(0.3)
        assert page.stats["events"] > before           # the publisher never waited for it
        stuck.close()
    finally:
        page.close()


class _QuietState:
    """A state that never changes after its first snapshot (a daemon whose device went quiet)."""

    def __init__(self):
        self.seq = 0

    def wait(self, seq, timeout):
        if self.seq == 0:
            self.seq = 1
        else:
            time.sleep(timeout)
        return self.seq

    def build(self):
        return {"seq": self.seq, "coverage": 0.1}


def test_closed_stream_frees_its_slot_without_any_event():
    page = LivePage(_QuietState(), "127.0.0.1", 0, max_clients=2).start()
    try:
        url = page.url
        socks = [socket.create_connection(_addr(url), timeout=5.0) for _ in range(2)]
        for s in socks:
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            assert s.recv(64).startswith(b"HTTP/1.0 200")
        assert request(url, b"GET /events HTTP/1.1\r\n\r\n", timeout=1.0).startswith(b"HTTP/1.0 503")
        events = page.stats["events"]
        for s in socks:
            s.close()
        time.sleep(5 * PEER_CHECK_S)
        assert page.stats["events"] == events          # nothing was written that could fail
        assert page.n_clients == 0
    finally:
        page.close()


def test_token_required_when_given():
    page = LivePage(_FastState(), "127.0.0.1", 0, token="s3cret").start()
    try:
        url = page.url
        assert request(url, b"GET / HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 403")
        assert request(url, b"GET /?token=wrong HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 403")
        assert request(url, b"GET /?token=s3cret HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 200")
        assert request(url, b"GET /state.json HTTP/1.0\r\nX-Streamcal-Token: s3cret\r\n\r\n"
                       ).startswith(b"HTTP/1.0 200")
    finally:
        page.close()


def test_parse_http():
    assert parse_http("8080") == ("127.0.0.1", 8080)
    assert parse_http("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_http("[::1]:8080") == ("::1", 8080)
    from streamcal.errors import InputError
    with pytest.raises(InputError, match="--http"):
        parse_http("eighty")
    with pytest.raises(InputError, match="0..65535"):
        parse_http("70000")


@pytest.mark.slow
def test_non_loopback_warns_on_stderr(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-m", "streamcal", "daemon", "--bus", f"fake:{TRACK}",
                           "--no-socket", "--state-dir", str(tmp_path / "s2"), "--max-seconds",
                           "1", "--http", "0.0.0.0:0"], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=60)
    assert "warning: --http 0.0.0.0:0 listens beyond this machine" in done.stderr
    assert "--http-token" in done.stderr


@pytest.mark.slow
def test_serial_host_serves_the_page(tmp_path):
    """A fake board at 10× its pace: the events are read until one carries a calibration and
    a calibrated magnitude (a block applied with it; the capture that first sees a calibration
    may be of a poll without a block). The page stays up after the replay (until terminated),
    so however slow the machine, nothing races the end of the track."""
    proc, url = start_daemon(tmp_path, device=["serial", "--port", f"fake:{TRACK}", "--speed",
                                               "10"], seconds="300")
    try:
        events = sse_events(url, seconds=120.0, until=lambda e: e["calibration"] is not None
                            and any(v is not None for v in e["magnitude"]["calibrated"]))
        state = events[-1]
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert state["device"]["bus_errors_name"] == "frames lost"
    assert "restarts" in state["device"]["counters"]
    assert state["coverage"] > 0
    cal = state["calibration"]
    assert cal["version"] >= 1 and cal["rms"] > 0 and "inliers" in cal["residual"]
    assert state["fits"]["accepted"] >= 1
    accepted = [e for e in state["fits"]["recent"] if e["kind"] == "accepted"]
    assert accepted and accepted[-1]["reason"]            # the guard's named rule
    cal_mag = [v for v in state["magnitude"]["calibrated"] if v is not None]
    assert cal_mag and abs(cal_mag[-1] / cal["field"] - 1) < 0.5
    # no "after calibration" figure while there was no calibration
    before = [e for e in events if e["calibration"] is None]
    assert before, "the stream began after the first calibration: nothing checked"
    assert all(v is None for e in before for v in e["magnitude"]["calibrated"])


@pytest.mark.slow
def test_watched_replay_keeps_its_page_after_the_end(tmp_path):
    """``--http`` on a fake bus: the replay ends, the page stays with the final state (replay
    over, 0 samples/s) until SIGINT, which ends it cleanly."""
    proc, url = start_daemon(tmp_path, speed="60", seconds="300")
    lines = proc.stderr_lines
    try:
        assert lines.wait_for(r"replaying demo_track\.csv\.gz at 60× the recorded pace \(3 s\); "
                              r"--speed N to change; the page stays up after the end; Ctrl-C",
                              5), lines.text()
        over = lines.wait_for(r"replay over; the live page stays at (http://\S+) until Ctrl-C",
                              120)
        assert over and over.group(1) == url, lines.text()[-2000:]
        state = json.loads(request(url, b"GET /state.json HTTP/1.0\r\n\r\n").partition(
            b"\r\n\r\n")[2])
        assert state["device"]["state"] == "replay over"
        assert state["device"]["samples_per_s"] == 0
        assert state["device"]["samples"] > 0
        assert state["calibration"] is not None
        assert request(url, b"GET / HTTP/1.0\r\n\r\n").startswith(b"HTTP/1.0 200")
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert lines.wait_for(r"live page closed \(SIGINT\)", 5), lines.text()[-500:]
    with pytest.raises(OSError):
        request(url, b"GET / HTTP/1.0\r\n\r\n")


def _track_rows() -> int:
    from streamcal.inputs.track import Track

    track = Track.read(TRACK)
    return int(np.isfinite(track.mag).all(axis=1).sum())


@pytest.mark.slow
def test_watched_replay_follows_the_recorded_pace_by_default(tmp_path):
    """``daemon --bus fake: --http`` without ``--speed``: one stderr line says so, and the
    samples arrive at the track's own rate (full speed would be tens of times faster)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "streamcal", "daemon", "--bus", f"fake:{TRACK}",
                             "--no-socket", "--state-dir", str(tmp_path / "s"), "--http",
                             "127.0.0.1:0"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=REPO)
    lines = StderrLines(proc, tmp_path / "stderr.txt")
    try:
        found = lines.wait_for(r"replaying demo_track\.csv\.gz at the recorded pace \((\d+) s\); "
                               r"--speed N to change", 60)
        assert found, lines.text()
        from streamcal.inputs.track import Track

        track = Track.read(TRACK)
        assert int(found.group(1)) == round(track.t[-1] - track.t[0])
        url = lines.wait_for(r"live page at (http://[\d.]+:\d+/)", 5).group(1)
        events = sse_events(url, seconds=60.0, until=lambda e: e["device"]["samples"] > 0)
        first = events[-1]
        events = sse_events(url, seconds=60.0,
                            until=lambda e: e["uptime_s"] >= first["uptime_s"] + 4)
        last = events[-1]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    rate = _track_rows() / (track.t[-1] - track.t[0])            # samples per track second
    pace = (last["device"]["samples"] - first["device"]["samples"]) / rate / (
        last["uptime_s"] - first["uptime_s"])
    assert 0.7 < pace < 1.3, pace


def test_snapshot_before_and_after_the_first_calibration():
    """The bundled track through a streaming calibrator into a LiveState on the track's clock:
    before the first calibration no 'after calibration' magnitude (apply() then scales by the
    running sphere estimate, not a calibration); after it, calibrated values near the fitted
    field. Directions: unit vectors, at most MAX_DIRECTIONS, none before a sphere frames them."""
    from streamcal.inputs.track import Track
    from streamcal.service.live_state import MAX_DIRECTIONS, LiveState
    from streamcal.service.replay_feed import ReplayFeed
    from streamcal.stream import StreamingCalibrator

    track = Track.read(TRACK)
    now = [0.0]
    state = LiveState(clock=lambda: now[0])
    calibrator = StreamingCalibrator(synchronous=True, unit=track.mag_unit)
    feed = ReplayFeed(calibrator, [state])
    snaps = []
    for i, block in enumerate(track.blocks(50)):
        now[0] = float(block.t[-1])
        feed.observe(block, calibrator.ingest(block))
        if i % 8 == 0 or calibrator.calibration is not None:
            snaps.append(state.build())
        if calibrator.calibration is not None and now[0] > 40:
            break
    before = [s for s in snaps if s and s["calibration"] is None]
    after = [s for s in snaps if s and s["calibration"] is not None]
    assert before and after
    assert all(v is None for s in before for v in s["magnitude"]["calibrated"])
    assert any(v is not None for v in before[-1]["magnitude"]["raw"])
    cal = [v for v in after[-1]["magnitude"]["calibrated"] if v is not None]
    assert cal and abs(np.median(cal) / after[-1]["calibration"]["field"] - 1) < 0.05
    unframed = [s for s in snaps if s and s["coverage"] is None]
    assert unframed and all(s["directions"] == [] for s in unframed)
    d = np.array(after[-1]["directions"])
    assert 0 < len(d) <= MAX_DIRECTIONS and d.shape[1] == 3
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=3e-3)


@pytest.mark.slow
def test_realtime_replay_keeps_its_page_after_the_end(tmp_path):
    """``replay --realtime --http`` over a 3 s recording: after the summary the page stays with
    the final state until SIGINT (the exit code is still the replay's: 1, no calibration)."""
    from streamcal.sim.scenario import simulate

    track = tmp_path / "short.csv"
    simulate(3, seed=5, motor=False).track.write(track)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "streamcal", "replay", str(track), "--realtime",
                             "--http", "127.0.0.1:0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    lines = StderrLines(proc, tmp_path / "stderr.txt")
    try:
        over = lines.wait_for(r"replay over; the live page stays at (http://\S+) until Ctrl-C", 120)
        assert over, lines.text()[-2000:]
        state = json.loads(request(over.group(1), b"GET /state.json HTTP/1.0\r\n\r\n").partition(
            b"\r\n\r\n")[2])
        assert state["device"]["state"] == "replay over"
        assert state["device"]["samples_per_s"] == 0 and state["device"]["samples"] > 0
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 1
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "coverage" in proc.stdout.read()             # the summary came before the wait
    assert lines.wait_for(r"live page closed \(SIGINT\)", 5), lines.text()[-500:]


@pytest.mark.parametrize("device", [["serial", "--port", "/dev/ttyNOPE"],
                                    ["serial", "--port", f"simavr:{TRACK}"],
                                    ["daemon", "--bus", "1"]])
def test_speed_on_a_device_without_a_recorded_pace_is_one_line(tmp_path, device):
    done = subprocess.run([sys.executable, "-m", "streamcal", *device, "--speed", "2",
                           "--no-socket", "--state-dir", str(tmp_path / "s")],
                          capture_output=True, text=True, cwd=REPO, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
    assert "--speed applies to a fake:TRACK.csv device only" in done.stderr
    assert ("simavr runs as fast as the host reads" in done.stderr) == ("simavr:" in device[2])
