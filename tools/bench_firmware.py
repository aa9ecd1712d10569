#!/usr/bin/env python3
"""What the board's own calibration costs on an Uno: flash and RAM, and the fit's time on the board.

Baselines, measured in the same run:

* size: the same sketch built with ``-DSC_NO_SELFCAL`` (no fit, no coverage mask, no SELF_CAL
  frame); ratios are with / without, and the issue-#15 budget (14 KB flash, 1.2 KB RAM) is shown.
* time: the firmware runs the demo track in simavr (``SimavrBoard``) until its first window
  fills and is fitted. Each SELF_CAL frame reports the fit's cycles and the mean cycles of one
  magnetometer sample's self-calibration work (sums, coverage cell, held-out scores) over that
  window, both from ``micros()`` (4 µs = 64 cycles resolution at 16 MHz). The fit is compared
  with that per-sample work and with the 5 ms poll period (80 000 cycles) it holds the loop for
  (the sensors are still polled from inside the fit, one sample held).

    python tools/bench_firmware.py [--seconds 80]

Needs the toolchain of HARDWARE.md §7 (arduino-builder, avr-size, simavr, libsimavr-dev …).
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from _bench_common import run_stamp                                     # noqa: E402
from firmware_bridge.selfcal_frames import SelfCalEvent                  # noqa: E402
from firmware_bridge.simavr_board import SimavrBoard, missing_toolchain  # noqa: E402
from streamcal.inputs.track import Track                                 # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "streamcal" / "data" / "demo_track.csv.gz"
F_CPU = 16_000_000
PERIOD_CYCLES = 5e-3 * F_CPU             # the sketch's 5 ms poll
FLASH_BUDGET, RAM_BUDGET = 14 * 1024, 1228


def build_size(flags: str, where: Path) -> tuple[int, int]:
    """(flash, RAM) bytes from avr-size for the sketch built with SC_BUILD_FLAGS=flags."""
    env = dict(os.environ, SC_BUILD_FLAGS=flags)
    res = subprocess.run(["sh", str(REPO / "tools" / "build_sketch.sh"), str(where)], env=env,
                         capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        sys.exit(f"bench_firmware: build with SC_BUILD_FLAGS={flags!r} failed:\n{res.stderr[-2000:]}")
    flash = int(re.search(r"Program:\s+(\d+) bytes", res.stdout).group(1))
    ram = int(re.search(r"Data:\s+(\d+) bytes", res.stdout).group(1))
    return flash, ram


def demo_excerpt(seconds: float) -> Track:
    track = Track.read(DEMO)
    c, keep = track.columns, track.t < track.t[0] + seconds
    triple = lambda names: np.column_stack([c[n][keep] for n in names])  # noqa: E731
    return Track.from_arrays(track.t[keep], mag=triple(("mx", "my", "mz")), accel=triple(("ax", "ay", "az")),
                             gyro=triple(("gx", "gy", "gz")), temp=c["temp"][keep])


def self_cal_frames(seconds: float) -> list:
    track = demo_excerpt(seconds)
    with SimavrBoard(track, asa=(0xB0, 0xB2, 0xA5)) as board:
        link = board.open_link()
        for block in link.blocks(idle_timeout=10.0):
            if board.track_time(block.t[-1]) > track.t[-1] + 0.05:
                break
        frames = list(link.self_cal)
        link.close()
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=80.0, help="demo track replayed in simavr (s)")
    args = ap.parse_args()
    missing = missing_toolchain()
    if missing:
        sys.exit("bench_firmware: missing " + ", ".join(missing) + " (HARDWARE.md §7)")
    print(run_stamp())
    with tempfile.TemporaryDirectory() as tmp:
        base = build_size("-DSC_NO_SELFCAL", Path(tmp) / "base")
        full = build_size("", Path(tmp) / "full")
    print("\nsize on an Uno (avr-size; RAM = .data + .bss, the stack is the rest of the 2 KB)")
    print(f"{'':24}{'flash B':>10}{'RAM B':>10}")
    print(f"{'without (-DSC_NO_SELFCAL)':24}{base[0]:>10}{base[1]:>10}")
    print(f"{'with self-calibration':24}{full[0]:>10}{full[1]:>10}")
    print(f"{'with / without':24}{full[0] / base[0]:>10.2f}{full[1] / base[1]:>10.2f}")
    print(f"{'added':24}{full[0] - base[0]:>10}{full[1] - base[1]:>10}")
    print(f"{'issue #15 budget':24}{FLASH_BUDGET:>10}{RAM_BUDGET:>10}"
          f"   ({'within' if full[0] <= FLASH_BUDGET and full[1] <= RAM_BUDGET else 'OVER'})")

    frames = self_cal_frames(args.seconds)
    fits = [f for f in frames if f.event in (SelfCalEvent.FITTED, SelfCalEvent.FIT_FAILED)]
    if not fits:
        sys.exit(f"bench_firmware: no fit in {args.seconds:g} s of the demo track (first window fills at ~51 s)")
    print(f"\nfit on the board (simavr, 16 MHz; demo track, {len(fits)} window(s) in {args.seconds:g} s)")
    print(f"{'window':>7}{'samples':>9}{'fit cycles':>12}{'fit ms':>8}{'sample cycles':>15}"
          f"{'fit/sample':>12}{'fit/5 ms poll':>15}{'sample/10 ms':>14}")
    for i, f in enumerate(fits):
        per = f.sample_cycles
        print(f"{i:>7}{f.n_fit:>9}{f.fit_cycles:>12}{1e3 * f.fit_cycles / F_CPU:>8.2f}{per:>15}"
              f"{f.fit_cycles / per if per else float('nan'):>12.1f}{f.fit_cycles / PERIOD_CYCLES:>15.2f}"
              f"{per / (2 * PERIOD_CYCLES):>14.4f}")
    print("sample cycles: one magnetometer sample's self-calibration work (window mean); "
          "sample/10 ms: its share of the AK8963's 100 Hz period")


if __name__ == "__main__":
    main()
