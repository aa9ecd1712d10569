"""The live page server (``--http``): SSE events, limits, bad requests, slow clients, token."""
from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from streamcal.service.http_page import PEER_CHECK_S, LivePage, parse_http

REPO = Path(__file__).resolve().parent.parent
TRACK = REPO / "streamcal" / "data" / "demo_track.csv.gz"


def start_daemon(tmp_path, *extra, speed="3", seconds="60", device=None):
    """``streamcal daemon --bus fake:TRACK --speed SPEED --http 127.0.0.1:0`` (``device``: other
    leading arguments, e.g. ``serial --port fake:TRACK``); returns (process, base URL)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    err = open(tmp_path / "stderr.txt", "w+")
    device = device or ["daemon", "--bus", f"fake:{TRACK}", "--speed", speed]
    proc = subprocess.Popen([sys.executable, "-m", "streamcal", *device, "--no-socket", "--state-dir", str(tmp_path / "s"),
                             "--max-seconds", seconds, "--http", "127.0.0.1:0", *extra],
                            stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=REPO)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        err.seek(0)
        found = re.search(r"live page at (http://[\d.]+:\d+/)", err.read())
        if found:
            return proc, found.group(1)
        if proc.poll() is not None:
            err.seek(0)
            pytest.fail(f"daemon exited: {err.read()[-2000:]}")
        time.sleep(0.1)
    proc.kill()
    pytest.fail("daemon did not print the live page address")


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


def sse_events(url, path="/events", seconds=3.0) -> list[dict]:
    """JSON of the ``data:`` lines received on ``path`` during ``seconds``."""
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
    head, _, body = buf.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.0 200"), head[:200]
    assert b"Content-Type: text/event-stream" in head
    events = [json.loads(line[6:]) for line in body.split(b"\n") if line.startswith(b"data: ")]
    return events


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
    proc, url = start_daemon(tmp_path, device=["serial", "--port", f"fake:{TRACK}"], seconds="30")
    try:
        events = sse_events(url, seconds=3.0)
        deadline = time.monotonic() + 25
        while time.monotonic() < deadline:
            body = request(url, b"GET /state.json HTTP/1.0\r\n\r\n").partition(b"\r\n\r\n")[2]
            state = json.loads(body)
            if state and state["calibration"] is not None:
                break
            time.sleep(0.5)
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert events and events[-1]["device"]["bus_errors_name"] == "frames lost"
    assert "restarts" in events[-1]["device"]["counters"]
    assert events[-1]["coverage"] > 0
    cal = state["calibration"]
    assert cal is not None, state["fits"]
    assert cal["version"] >= 1 and cal["rms"] > 0 and "inliers" in cal["residual"]
    assert state["fits"]["accepted"] >= 1
    accepted = [e for e in state["fits"]["recent"] if e["kind"] == "accepted"]
    assert accepted and accepted[-1]["reason"]            # the guard's named rule
    cal_mag = [v for v in state["magnitude"]["calibrated"] if v is not None]
    assert cal_mag and abs(cal_mag[-1] / cal["field"] - 1) < 0.5
