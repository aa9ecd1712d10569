#!/usr/bin/env python3
"""Write the bundled demo track ``streamcal/data/demo_track.csv.gz``.

A 3-minute hand tumble of a simulated MPU-9250: magnetometer at 100 Hz (16-bit, 0.4 µT noise),
accelerometer/gyro/temperature at 200 Hz on their own rows, a ``motor_current`` auxiliary
channel, soft and hard iron, a board warming up by about 15 °C, one hidden effect and one short
outlier burst (a phone passing by). The track's metadata says it is simulated (seed, tool
version) but not which effect is hidden: finding it is the demo's job.

    python tools/make_demo_track.py [-o PATH] [--seed N] [--truth TRUTH.json]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from streamcal.sim import simulate  # noqa: E402

TOOL_VERSION = "1"
DEFAULT_OUT = Path(__file__).resolve().parent.parent / "streamcal" / "data" / "demo_track.csv.gz"
SEED = 20261121
#: The hidden effect: offset drifting 0.3 µT/°C (≈ 4.5 µT over the warm-up, ten times the noise).
HIDDEN = {"temperature_offset": 0.3}


def make(seed: int = SEED):
    """The demo session (a :class:`streamcal.sim.SimResult`)."""
    return simulate(duration_s=180.0, seed=seed, effects=HIDDEN, noise_uT=0.4, mag_bits=16,
                    mag_rate_hz=100.0, imu_rate_hz=200.0, coverage="full", outlier_bursts=1,
                    burst_uT=120.0, temp_profile="warmup", temp_start_c=21.0, temp_delta_c=15.0,
                    motor=True, metadata={"tool": f"tools/make_demo_track.py {TOOL_VERSION}",
                                          "description": "simulated 3-minute hand tumble"})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--truth", type=Path, help="also write the truth (JSON) here")
    args = ap.parse_args(argv)
    result = make(args.seed)
    result.write(args.output, truth_path=args.truth)
    size = os.path.getsize(args.output)
    print(f"wrote {args.output} ({size / 1e6:.2f} MB, {len(result.track.t)} rows, "
          f"outlier span {result.truth.outlier_spans.round(2).tolist()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
