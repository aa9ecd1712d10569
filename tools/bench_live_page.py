"""Benchmark: what the live page (``--http``) costs the sensor path.

The daemon loop (:class:`streamcal.service.Service`: fake-bus driver → streaming calibrator with
fits on the worker thread → store; no sample outputs, so the page's share is as large as it can
be) runs over the demo track as fast as it can be read (``--bus fake:TRACK``, time continued over
``--laps`` laps, as ``tools/bench_daemon.py`` measures it), alternately without the page
(baseline) and with the page and one SSE client reading every event, ``--repeats`` times each
in the same run. Reported: the median samples/s of each, their ratio and the median ratio of
the paired runs (target ≥ 0.95), the process CPU time per sample with and without (the cost the
page adds, all its threads included, which other load on the machine does not blur) and the
events the client received per wall second (the page must still update ≥ 2 per second).

    python tools/bench_live_page.py [--track T.csv.gz] [--laps 5] [--repeats 5] [--json]

Five laps (90 000 samples, ~7 s a run) by default: the daemon runs for hours, and in a 1-lap run
(1.3 s) the page's start and the first snapshot sent to a new client weigh several per cent
(1-lap runs on an idle machine: 0.944–0.949; 5-lap runs: 0.963–0.985, RESULTS.md §5).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_daemon import Laps  # noqa: E402
from streamcal.service import Notifier, Outputs, Service  # noqa: E402
from streamcal.service.http_page import LivePage  # noqa: E402
from streamcal.service.live_state import LiveState  # noqa: E402
from streamcal.stream import CalibrationStore, StreamingCalibrator  # noqa: E402


class _Observer:
    def __init__(self, state, page):
        self.state, self.page = state, page
        self.on_block, self.on_events = state.on_block, state.on_events

    def close(self):
        self.state.close()
        self.page.close()


_CLIENT = r"""
import socket, sys, time
host, port = sys.argv[1], int(sys.argv[2])
events = nbytes = 0
with socket.create_connection((host, port), timeout=0.5) as s:
    s.sendall(b"GET /events HTTP/1.1\r\nHost: bench\r\n\r\n")
    sys.stdout.write("connected\n"); sys.stdout.flush()
    while True:
        try:
            chunk = s.recv(1 << 16)
        except socket.timeout:
            continue
        if not chunk:
            break
        events += chunk.count(b"\ndata: ") + chunk.startswith(b"data: ")
        nbytes += len(chunk)
print(events, nbytes)
"""


def _start_client(url: str) -> subprocess.Popen:
    """An SSE reader in its own process, as a browser is: it takes no time of the daemon's
    process (its CPU and the interpreter lock stay the daemon's)."""
    host, port = url.split("//")[1].rstrip("/").split(":")
    proc = subprocess.Popen([sys.executable, "-c", _CLIENT, host, port], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "connected"
    return proc


def one_run(track: str, laps: int, page: bool) -> dict:
    d = Path(tempfile.mkdtemp(prefix="sclp", dir="/tmp"))
    store = CalibrationStore(d / "state")
    observers, counts = [], {"events": 0, "bytes": 0}
    reader = live = None
    if page:
        state = LiveState()
        live = LivePage(state, "127.0.0.1", 0).start()
        observers.append(_Observer(state, live))
        reader = _start_client(live.url)
        time.sleep(0.2)                      # the stream is open before the loop starts
    service = Service(lambda buffer=None: StreamingCalibrator(store=store), Laps(track, laps, []),
                      outputs=Outputs([]), notifier=Notifier(environ={}), log=lambda line: None,
                      observers=observers)
    t0, c0 = time.perf_counter(), time.process_time()
    service.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if reader is not None:
        live.close()              # (the service closed it already) the client prints its counts
        events, nbytes = reader.communicate(timeout=10)[0].split()
        counts.update(events=int(events), bytes=int(nbytes))
    return {"samples": service.stats.samples, "seconds": wall, "cpu_s": cpu,
            "rate": service.stats.samples / wall, "events": counts["events"],
            "events_per_s": counts["events"] / wall, "bytes": counts["bytes"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--track", default=str(REPO / "streamcal" / "data" / "demo_track.csv.gz"))
    p.add_argument("--laps", type=int, default=5)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    runs = {False: [], True: []}
    for _ in range(a.repeats):               # interleaved: drifts in machine load hit both
        for page in (False, True):
            runs[page].append(one_run(a.track, a.laps, page))
    base = statistics.median(r["rate"] for r in runs[False])
    live = statistics.median(r["rate"] for r in runs[True])
    paired = statistics.median(b["rate"] / a["rate"] for a, b in zip(runs[False], runs[True]))
    cpu = {k: statistics.median(1e6 * r["cpu_s"] / r["samples"] for r in v) for k, v in runs.items()}
    eps = statistics.median(r["events_per_s"] for r in runs[True])
    out = {"track": a.track, "laps": a.laps, "repeats": a.repeats,
           "baseline_samples_per_s": round(base), "with_page_samples_per_s": round(live),
           "ratio_with_to_without": round(live / base, 3),
           "median_paired_ratio": round(paired, 3),
           "cpu_us_per_sample_without": round(cpu[False], 1),
           "cpu_us_per_sample_with": round(cpu[True], 1),
           "cpu_ratio_with_to_without": round(cpu[True] / cpu[False], 3),
           "client_events_per_s": round(eps, 2),
           "baseline_rates": [round(r["rate"]) for r in runs[False]],
           "with_page_rates": [round(r["rate"]) for r in runs[True]],
           "samples_per_run": runs[False][0]["samples"]}
    if a.json:
        print(json.dumps(out))
        return 0
    print(f"track {Path(a.track).name}: {out['samples_per_run']} samples per run "
          f"({a.laps} laps), {a.repeats} runs each, interleaved")
    print(f"daemon loop without page (baseline) {base:10.0f} samples/s  runs {out['baseline_rates']}")
    print(f"daemon loop with page + SSE client  {live:10.0f} samples/s  runs {out['with_page_rates']}")
    print(f"ratio with/without {live / base:.3f}, median of the paired runs' ratios {paired:.3f} "
          f"(target >= 0.95); the client received {eps:.2f} events/s")
    print(f"process CPU per sample (all threads: loop, fits, page) without {cpu[False]:.1f} µs, "
          f"with {cpu[True]:.1f} µs: ratio {cpu[True] / cpu[False]:.3f} (wall rates on a shared "
          "machine vary run to run; the CPU the page adds does not depend on the neighbours)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
