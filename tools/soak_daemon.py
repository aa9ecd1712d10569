"""Soak test of the daemon's service loop: hours of simulated 100 Hz data, as fast as it runs.

The real pieces, end to end: :class:`~streamcal.service.daemon.Service` (the loop of
``streamcal daemon``) → the MPU-9250 driver → a register-level :class:`FakeMPU9250Bus`, with the
streaming calibrator, its worker-thread fits, the calibration store in a state directory and a
JSON-lines output (to /dev/null). The track is simulated in ``--chunk-s`` pieces
(``streamcal.sim.simulate``, one fixed sensor, fresh motion and one phone passing per piece); a
few distinct pieces are synthesized once and looped with continuing time, each served by a new
fake bus (the driver sees a device that comes back at power-on defaults and re-initialises it).

Recorded every ``--rss-every`` magnetometer samples: resident memory (``VmRSS`` from
``/proc/self/status``), wall time, samples, calibrator events and errors. At the end: wall time,
rate (simulated hours per wall hour), the memory curve and whether it is flat (max/min after
warm-up within ``--flat`` = 10 %), disk use of the state directory, and the environment events
(``drift``/``forgot``/``recalled`` for changes, ``disturbance`` for transients such as the
simulated phones: one per piece is expected). ``--max-wall S`` stops early;
the report then extrapolates the full duration from the measured rate and says so.

    python tools/soak_daemon.py --hours 24                # the full soak (about 25 min here)
    python tools/soak_daemon.py --hours 24 --max-wall 600 --json soak.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from firmware_bridge.fake_mpu9250 import FakeMPU9250Bus  # noqa: E402
from firmware_bridge.mpu9250 import MPU9250, DeviceError  # noqa: E402
from streamcal.service import Notifier, Outputs, Service, StreamOutput  # noqa: E402
from streamcal.service.sources import SourceUnavailable  # noqa: E402
from streamcal.sim import simulate  # noqa: E402
from streamcal.stream import CalibrationStore, StreamingCalibrator  # noqa: E402

TRUE_K = np.array([[47.0, 0.8, -1.1], [0.0, 45.5, 0.6], [0.0, 0.0, 49.0]])
TRUE_B = np.array([12.0, -7.5, 4.0])


def vm_rss_kb() -> int:
    """Resident set size of this process, kB (``VmRSS`` of /proc/self/status)."""
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


def dir_bytes(path: Path) -> tuple[int, int]:
    """(bytes, files) under ``path``."""
    total = files = 0
    for root, _, names in os.walk(path):
        for name in names:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
                files += 1
            except FileNotFoundError:
                pass
    return total, files


def make_chunks(n: int, chunk_s: float, seed: int):
    """``n`` distinct simulated pieces: dicts of arrays (t from 0, mag µT, accel, gyro, temp)."""
    out = []
    for k in range(n):
        tr = simulate(chunk_s, seed=seed + k, K=TRUE_K, b=TRUE_B, imu_rate_hz=100.0,
                      motor=False, outlier_bursts=1, temp_profile="constant").track
        cols = tr.columns
        out.append({"t": np.asarray(tr.t) - tr.t[0],
                    "mag": np.column_stack([cols[c] for c in ("mx", "my", "mz")]),
                    "accel": np.column_stack([cols[c] for c in ("ax", "ay", "az")]),
                    "gyro": np.column_stack([cols[c] for c in ("gx", "gy", "gz")]),
                    "temp": cols["temp"], "n_mag": int(tr.mag_rows.sum())})
    return out


class LoopedFakeI2C:
    """A service source (the :mod:`streamcal.service.sources` interface) replaying simulated
    pieces back to back with continuing time, each on a fresh fake bus, until ``hours``."""

    def __init__(self, chunks, chunk_s: float, hours: float, *, block_size: int = 50,
                 on_samples=None):
        self.chunks, self.chunk_s = chunks, float(chunk_s)
        self.n_pieces = max(1, math.ceil(hours * 3600.0 / self.chunk_s))
        self.block_size = block_size
        self.on_samples = on_samples
        self.piece = -1
        self.samples = 0
        self.totals = {"samples": 0, "retries": 0, "failures": 0, "reinits": 0}
        self.description = f"looped fake i2c ({self.n_pieces} × {self.chunk_s:g} s)"
        self.sleep = lambda s: None
        self._next_piece()

    def _next_piece(self) -> None:
        if self.piece >= 0:
            for key in self.totals:
                self.totals[key] += self.driver.stats.get(key, 0)
        self.piece += 1
        c = self.chunks[self.piece % len(self.chunks)]
        offset = self.piece * self.chunk_s
        self.bus = FakeMPU9250Bus(c["t"] + offset, mag=c["mag"], accel=c["accel"],
                                  gyro=c["gyro"], temp=c["temp"], seed=self.piece)
        self.driver = MPU9250(self.bus, init=False, clock=self.bus.now, sleep=lambda s: None)
        self.up = False

    @property
    def finished(self) -> bool:
        return self.piece >= self.n_pieces - 1 and self.bus.finished

    def read(self):
        if self.bus.finished and self.piece < self.n_pieces - 1:
            self._next_piece()
        try:
            if not self.up:
                self.driver.init()
                self.up = True
            block = self.driver.read_block(self.block_size, timeout=1.0, source="soak")
        except DeviceError as exc:
            raise SourceUnavailable(str(exc)) from exc
        if not len(block):
            return None
        self.samples += int(np.count_nonzero(block.mag_valid))
        if self.on_samples is not None:
            self.on_samples(self.samples)
        return block

    def counters(self) -> dict:
        s = self.driver.stats
        return {"samples": self.totals["samples"] + s.get("samples", 0),
                "bus_errors": self.totals["failures"] + s.get("failures", 0),
                "retries": self.totals["retries"] + s.get("retries", 0),
                "reinits": self.totals["reinits"] + s.get("reinits", 0), "pieces": self.piece + 1}

    def close(self) -> None:
        pass


def soak(hours: float = 24.0, *, chunk_s: float = 600.0, distinct: int = 3, seed: int = 1,
         rss_every: int = 100_000, state_dir: str | None = None, max_wall: float | None = None,
         sync_fits: bool = False, warmup_fraction: float = 0.2, flat: float = 0.10,
         log=None) -> dict:
    """Run the soak; returns the report (JSON-ready). See the module docstring."""
    say = log or (lambda line: None)
    t_setup = time.perf_counter()
    chunks = make_chunks(distinct, chunk_s, seed)
    setup_s = time.perf_counter() - t_setup
    own_dir = state_dir is None
    state = Path(tempfile.mkdtemp(prefix="soak-state-") if own_dir else state_dir)
    store = CalibrationStore(state)
    curve: list[dict] = []
    lines: list[str] = []
    n_lines = [0]
    start = [0.0]
    service_ref: list[Service] = []

    def record(samples: int) -> None:
        if samples < (len(curve)) * rss_every:
            return
        service = service_ref[0]
        wall = time.perf_counter() - start[0]
        point = {"samples": samples, "sim_hours": round(samples / 100.0 / 3600.0, 4),
                 "wall_s": round(wall, 2), "rss_kb": vm_rss_kb(),
                 "events": dict(service.stats.events),
                 "ingest_errors": service.stats.ingest_errors,
                 "buffer_samples": int(service.calibrator.buffer.n_samples)
                 if service.calibrator is not None else 0,
                 "buffer_capacity": int(service.calibrator.buffer.capacity)
                 if service.calibrator is not None else 0}
        curve.append(point)
        say(f"{point['sim_hours']:8.3f} h simulated  {wall:8.1f} s wall  "
            f"RSS {point['rss_kb'] / 1024:7.1f} MB  buffer {point['buffer_samples']}  "
            f"accepted {point['events'].get('accepted', 0)}  errors {point['ingest_errors']}")
        if max_wall is not None and wall >= max_wall:
            service.request_stop(f"--max-wall {max_wall:g} s reached")

    source = LoopedFakeI2C(chunks, chunk_s, hours, on_samples=record)

    def make_calibrator(buffer=None):
        kwargs = {"buffer": buffer} if buffer is not None else {}
        return StreamingCalibrator(store=store, synchronous=sync_fits, **kwargs)

    def keep_log(line: str) -> None:
        n_lines[0] += 1
        lines.append(line)
        del lines[:-20]

    devnull = open(os.devnull, "w")
    service = Service(make_calibrator, source, outputs=Outputs([StreamOutput(devnull)]),
                      notifier=Notifier(environ={}), log=keep_log, name="soak")
    service_ref.append(service)
    start[0] = time.perf_counter()
    code = service.run()
    wall = time.perf_counter() - start[0]
    devnull.close()
    samples = service.stats.samples
    sim_h = samples / 100.0 / 3600.0
    rate = sim_h / (wall / 3600.0) if wall > 0 else float("nan")
    after = [p["rss_kb"] for p in curve if p["sim_hours"] >= warmup_fraction * sim_h]
    flat_ratio = (max(after) / min(after) - 1.0) if len(after) >= 2 else None
    disk, files = dir_bytes(state)
    cal = service.calibrator.calibration
    report = {
        "hours_requested": hours, "hours_simulated": round(sim_h, 4),
        "mag_samples": samples, "wall_s": round(wall, 2), "setup_s": round(setup_s, 2),
        "rate_sim_h_per_wall_h": round(rate, 2),
        "extrapolated_wall_s_for_requested": round(hours / rate * 3600.0, 1)
        if rate and math.isfinite(rate) else None,
        "complete": sim_h >= 0.999 * hours, "exit_code": code,
        "stop_reason": service.stats.stop_reason,
        "events": dict(service.stats.events),
        "environment_events": {k: service.stats.events.get(k, 0)
                               for k in ("drift", "forgot", "recalled", "disturbance")},
        "ingest_errors": service.stats.ingest_errors,
        "outages": service.stats.outages, "source": source.counters(),
        "output_lines": service.outputs.lines, "log_lines": n_lines[0], "last_log": lines[-5:],
        "rss_kb_first": curve[0]["rss_kb"] if curve else None,
        "rss_kb_after_warmup_min": min(after) if after else None,
        "rss_kb_after_warmup_max": max(after) if after else None,
        "rss_growth_after_warmup": None if flat_ratio is None else round(flat_ratio, 4),
        "rss_flat_within": flat, "rss_flat": None if flat_ratio is None else flat_ratio <= flat,
        "state_dir_bytes": disk, "state_dir_files": files,
        "model_error_vs_truth": None if cal is None else round(float(
            np.linalg.norm(np.hstack([cal.K, cal.b[:, None]]) - np.hstack([TRUE_K, TRUE_B[:, None]]))
            / np.linalg.norm(np.hstack([TRUE_K, TRUE_B[:, None]]))), 5),
        "curve": [{k: p[k] for k in ("sim_hours", "wall_s", "rss_kb", "buffer_samples",
                                     "buffer_capacity", "ingest_errors")} for p in curve],
    }
    if own_dir:
        import shutil
        shutil.rmtree(state, ignore_errors=True)
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--hours", type=float, default=24.0, help="simulated hours (default 24)")
    p.add_argument("--chunk-s", type=float, default=600.0, help="simulated piece length, s")
    p.add_argument("--distinct", type=int, default=3, help="distinct pieces looped")
    p.add_argument("--rss-every", type=int, default=100_000, help="mag samples between records")
    p.add_argument("--max-wall", type=float, help="stop after this many wall seconds")
    p.add_argument("--state-dir", help="keep the state directory here (default: a temp dir)")
    p.add_argument("--sync-fits", action="store_true", help="fit inline (deterministic)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", metavar="PATH", help="write the report as JSON")
    args = p.parse_args(argv)
    report = soak(args.hours, chunk_s=args.chunk_s, distinct=args.distinct, seed=args.seed,
                  rss_every=args.rss_every, state_dir=args.state_dir, max_wall=args.max_wall,
                  sync_fits=args.sync_fits, log=lambda line: print(line, flush=True))
    summary = {k: v for k, v in report.items() if k != "curve"}
    print(json.dumps(summary, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
    return 0 if report["ingest_errors"] == 0 and report["exit_code"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
