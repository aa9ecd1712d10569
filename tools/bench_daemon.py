"""Benchmark: samples/s the daemon loop sustains over the fake bus, against the raw driver.

Baseline (same run, same machine): ``MPU9250.read_block`` alone on a stepped
``FakeMPU9250Bus`` replaying the track — the fastest the driver path can deliver. Then the whole
daemon loop (:class:`streamcal.service.Service`: driver → streaming calibrator with fits on the
worker thread → store → JSON-lines output to /dev/null and a socket with one reading client) over
the same track, repeated ``--laps`` times with time continued, sampling the process RSS as it goes
(memory must stay flat: the buffer and the queues are bounded, not the uptime).

    python tools/bench_daemon.py [--track T.csv.gz] [--laps 5]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from firmware_bridge.ports import open_bus  # noqa: E402
from streamcal.inputs.track import Track  # noqa: E402
from firmware_bridge.mpu9250 import MPU9250  # noqa: E402
from streamcal.service import I2CBlocks, Notifier, Outputs, Service, SocketOutput, StreamOutput  # noqa: E402
from streamcal.stream import CalibrationStore, StreamingCalibrator  # noqa: E402


def rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def driver_rate(track: str) -> tuple[float, int]:
    bus = open_bus(f"fake:{track}", read_track=Track.read)
    drv = MPU9250(bus, clock=bus.now, sleep=lambda s: None)
    n, t0 = 0, time.perf_counter()
    while not bus.finished:
        n += len(drv.read_block(50))
    return n / (time.perf_counter() - t0), n


class Laps:
    """I2CBlocks over the track ``laps`` times, time continued from lap to lap."""

    def __init__(self, track: str, laps: int, rss: list):
        self.track, self.laps, self.rss = track, laps, rss
        self.lap, self.offset, self.t_last = 0, 0.0, 0.0
        self.src = I2CBlocks(f"fake:{track}")
        self.description, self.sleep = self.src.description, self.src.sleep
        self.t0 = time.perf_counter()
        self.blocks = 0

    @property
    def finished(self):
        return self.lap >= self.laps

    def read(self):
        if self.src.finished:
            self.lap += 1
            self.offset = self.t_last + 0.01
            self.src.close()
            if self.finished:
                return None
            self.src = I2CBlocks(f"fake:{self.track}")
        block = self.src.read()
        if block is None:
            return None
        self.blocks += 1
        if self.blocks % 50 == 0:
            self.rss.append((round(time.perf_counter() - self.t0, 2), round(rss_mib(), 1)))
        block = dataclasses.replace(block, t=block.t + self.offset)
        self.t_last = float(block.t[-1])
        return block

    def counters(self):
        return self.src.counters()

    def close(self):
        self.src.close()


def daemon_rate(track: str, laps: int) -> dict:
    d = Path(tempfile.mkdtemp(prefix="scb", dir="/tmp"))
    store = CalibrationStore(d / "state")
    sock = SocketOutput(d / "s.sock")
    client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    client.connect(os.fspath(d / "s.sock"))
    got = [0]

    def drain():
        while chunk := client.recv(1 << 16):
            got[0] += chunk.count(b"\n")
    threading.Thread(target=drain, daemon=True).start()
    rss: list = [(0.0, round(rss_mib(), 1))]
    source = Laps(track, laps, rss)
    devnull = open(os.devnull, "w")
    service = Service(lambda buffer=None: StreamingCalibrator(store=store), source,
                      outputs=Outputs([StreamOutput(devnull), sock]),
                      notifier=Notifier(environ={}), log=lambda line: None)
    t0 = time.perf_counter()
    service.run()
    wall = time.perf_counter() - t0
    time.sleep(0.2)
    return {"samples": service.stats.samples, "seconds": round(wall, 2),
            "rate": service.stats.samples / wall, "fits": service.stats.events.get("fit_started", 0),
            "accepted": service.stats.events.get("accepted", 0), "lines_out": service.outputs.lines,
            "lines_to_client": got[0], "dropped_for_client": sock.dropped_lines, "rss_mib": rss}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--track", default=str(REPO / "streamcal" / "data" / "demo_track.csv.gz"))
    p.add_argument("--laps", type=int, default=5)
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    base, n = driver_rate(a.track)
    run = daemon_rate(a.track, a.laps)
    rss = [m for _, m in run["rss_mib"]]
    half = len(rss) // 2
    out = {"track": a.track, "driver_samples_per_s": round(base), "daemon_samples_per_s": round(run["rate"]),
           "ratio_daemon_to_driver": round(run["rate"] / base, 3),
           "realtime_factor_at_100Hz": round(run["rate"] / 100.0), **run,
           "rss_first_half_max_mib": max(rss[:half] or rss), "rss_second_half_max_mib": max(rss[half:])}
    if a.json:
        print(json.dumps(out))
        return 0
    print(f"track {Path(a.track).name}: {n} magnetometer samples per lap, {a.laps} laps")
    print(f"raw driver read_block (baseline)  {base:10.0f} samples/s")
    print(f"daemon loop (fits, store, output) {run['rate']:10.0f} samples/s   "
          f"ratio {run['rate'] / base:.2f}   = {run['rate'] / 100:.0f}x the 100 Hz sensor rate")
    print(f"fits {run['fits']} (accepted {run['accepted']}), lines out {run['lines_out']}, "
          f"to the socket client {run['lines_to_client']} (dropped {run['dropped_for_client']})")
    print("RSS MiB over time (s, MiB): " + ", ".join(f"{t:g}:{m:g}" for t, m in run["rss_mib"][::max(1, len(rss) // 12)]))
    print(f"RSS max first half {out['rss_first_half_max_mib']} MiB, second half "
          f"{out['rss_second_half_max_mib']} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
