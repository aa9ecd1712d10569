"""Soak of the live page: the daemon's memory over an hour of track with SSE clients attached.

    python tools/soak_live_page.py [--hours 1] [--speed 20] [--track T.csv.gz] [--json OUT]

Runs ``streamcal daemon --bus fake:TRACK --speed S --http 127.0.0.1:0`` over a simulated
``--hours`` 100 Hz track (``streamcal.sim.simulate`` in hour segments, as
``bench_replay_memory`` makes them; or ``--track``), replayed at ``S`` times real time, with
three clients of ``/events``:

* ``steady``: reads all the time;
* ``slow``: reads ``--slow-bytes`` every ``--slow-every`` s (may be dropped by the server's
  per-client queue limit; it then reconnects);
* ``vanish``: connects, reads for ``--vanish-read`` s and closes, every ``--vanish-every`` s.

Every ``--sample-every`` s the daemon's ``VmRSS`` (``/proc/PID/status``) is sampled. Reported:
the RSS after warm-up (the first ``--warmup`` fraction of the run), at the end and its maximum,
the least-squares slope of RSS after warm-up against simulated time (MiB per simulated hour;
simulated time = wall time since the page came up × speed), the events each client received and
how often the server dropped a client (its stream ended, was reset or sent nothing for 5 s
while the daemon was still running; reconnects after the daemon's exit are not counted).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from _bench_common import REPO


def vm_rss_kib(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class Client(threading.Thread):
    """One ``/events`` reader; ``mode`` is steady, slow or vanish (module docstring)."""

    def __init__(self, addr, mode: str, args, stop: threading.Event, alive):
        super().__init__(daemon=True, name=mode)
        self.addr, self.mode, self.args, self.stop, self.alive = addr, mode, args, stop, alive
        self.events = self.connects = self.dropped = self.refused = 0
        self.last: dict | None = None
        self.drop_times: list[float] = []          # monotonic instants of the drops

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self._session()
            except OSError:            # reset, refused or 5 s without a byte
                if not self.stop.is_set() and self.alive():
                    self.dropped += 1
                    self.drop_times.append(time.monotonic())
            if self.mode == "vanish":
                self.stop.wait(self.args.vanish_every)
            else:
                self.stop.wait(0.2)

    def _session(self) -> None:
        with socket.create_connection(self.addr, timeout=5.0) as s:
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            self.connects += 1
            buf, began = b"", time.monotonic()
            while not self.stop.is_set():
                if self.mode == "vanish" and time.monotonic() - began > self.args.vanish_read:
                    return                              # close abruptly, mid-stream
                if self.mode == "slow":
                    self.stop.wait(self.args.slow_every)
                    chunk = s.recv(self.args.slow_bytes)
                else:
                    chunk = s.recv(65536)
                if not chunk:                           # the server ended the stream
                    if b" 503 " in buf[:40]:
                        self.refused += 1
                    elif not self.stop.is_set() and self.alive():
                        self.dropped += 1
                        self.drop_times.append(time.monotonic())
                    return
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for line in lines:
                    if line.startswith(b"data: "):
                        self.events += 1
                        if self.mode == "steady":
                            self.last = json.loads(line[6:])


def _track(args, tmp: Path) -> Path:
    if args.track:
        return Path(args.track)
    from bench_replay_memory import _make

    path = tmp / "soak.csv.gz"
    start = time.perf_counter()
    rows = _make(path, 3600 * args.hours, seed=3)
    print(f"simulated {path.name}: {args.hours:g} h, {rows} rows in "
          f"{time.perf_counter() - start:.0f} s", flush=True)
    return path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--speed", type=float, default=20.0)
    ap.add_argument("--track")
    ap.add_argument("--sample-every", type=float, default=3.0)
    ap.add_argument("--warmup", type=float, default=0.1)
    ap.add_argument("--slow-every", type=float, default=1.0)
    ap.add_argument("--slow-bytes", type=int, default=512)
    ap.add_argument("--vanish-every", type=float, default=3.0)
    ap.add_argument("--vanish-read", type=float, default=0.5)
    ap.add_argument("--json", metavar="OUT")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="soak_live_") as tmp_name:
        tmp = Path(tmp_name)
        track = _track(args, tmp)
        wall = 3600 * args.hours / args.speed
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        err = open(tmp / "stderr.txt", "w+")
        proc = subprocess.Popen(
            [sys.executable, "-m", "streamcal", "daemon", "--bus", f"fake:{track}", "--speed",
             str(args.speed), "--no-socket", "--state-dir", str(tmp / "state"),
             "--max-seconds", str(wall), "--http", "127.0.0.1:0"],
            stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=REPO)
        try:
            return _soak(args, proc, err, wall)
        finally:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30)


def _soak(args, proc, err, wall: float) -> int:
    deadline = time.monotonic() + 120
    while True:
        err.seek(0)
        found = re.search(r"live page at http://([\d.]+):(\d+)/", err.read())
        if found:
            break
        if proc.poll() is not None or time.monotonic() > deadline:
            err.seek(0)
            sys.exit(f"daemon did not start its page: {err.read()[-2000:]}")
        time.sleep(0.1)
    addr = (found.group(1), int(found.group(2)))
    start = time.monotonic()
    stop = threading.Event()
    clients = [Client(addr, mode, args, stop, lambda: proc.poll() is None) for mode in ("steady", "slow", "vanish")]
    for c in clients:
        c.start()
    samples: list[tuple[float, int]] = []
    while proc.poll() is None:
        rss = vm_rss_kib(proc.pid)
        if rss is not None:
            samples.append((time.monotonic() - start, rss))
        time.sleep(args.sample_every)
    alive_s = time.monotonic() - start
    stop.set()
    for c in clients:
        c.join(timeout=10)
    err.seek(0)
    tail = err.read()[-600:]
    t = np.array([s[0] for s in samples]) * args.speed / 3600.0   # simulated hours
    rss = np.array([s[1] for s in samples]) / 1024.0              # MiB
    after = t >= args.warmup * t[-1]
    slope = float(np.polyfit(t[after], rss[after], 1)[0]) if after.sum() >= 3 else float("nan")
    steady = clients[0].last or {}
    out = {
        "speed": args.speed, "simulated_h": float(alive_s * args.speed / 3600),
        "wall_s": alive_s, "planned_wall_s": wall, "daemon_rc": proc.returncode,
        "samples": len(samples), "rss_after_warmup_mib": float(rss[after][0]),
        "rss_end_mib": float(rss[-1]), "rss_max_after_warmup_mib": float(rss[after].max()),
        "rss_min_after_warmup_mib": float(rss[after].min()),
        "slope_mib_per_sim_h": slope,
        "clients": {c.mode: {"events": c.events, "connects": c.connects,
                             "dropped_by_server": c.dropped, "refused_503": c.refused,
                             "dropped_at_s": [round(d - start, 1) for d in c.drop_times]}
                    for c in clients},
        "last_event_device": steady.get("device"),
        "curve": [[round(float(a), 4), round(float(b), 1)] for a, b in zip(t, rss)],
    }
    print(f"daemon ran {alive_s:.0f} s wall at --speed {args.speed:g} = "
          f"{out['simulated_h']:.2f} simulated h (rc {proc.returncode}); {len(samples)} RSS "
          f"samples every {args.sample_every:g} s")
    print(f"VmRSS after warm-up ({args.warmup:.0%} of the run): "
          f"{out['rss_after_warmup_mib']:.1f} MiB; end {out['rss_end_mib']:.1f}; range after "
          f"warm-up {out['rss_min_after_warmup_mib']:.1f}..{out['rss_max_after_warmup_mib']:.1f}")
    print(f"slope after warm-up: {slope:+.2f} MiB per simulated hour (least squares)")
    for mode, c in out["clients"].items():
        print(f"client {mode:<7} events {c['events']:>6}  connects {c['connects']:>5}  "
              f"dropped by server {c['dropped_by_server']:>4} (at {c['dropped_at_s']} s of "
              f"{alive_s:.0f})  refused 503 {c['refused_503']}")
    print(f"last event's device block: {out['last_event_device']}")
    print(f"daemon stderr tail: {tail.strip()[-300:]}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
