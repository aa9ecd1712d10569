"""Benchmark (issue #10 speed target): convert + diagnose of a 20-minute flight log against the
autopilot's own calibration, beside a plain fit of the same samples timed in the same run.

    python tools/bench_flight.py [--log PATH] [--repeats 3]

Target: read + diagnose ≤ 10 s for ``ardupilot_erle_PXFv2.0b_Rpi.BIN`` (1231 s, 4675 MAG
samples). Timed (median of ``--repeats``, after one warm-up):

* ``read``: :func:`streamcal.inputs.read_recording` (DataFlash → Track, offsets undone; the
  bulk decoder of :mod:`streamcal.inputs.dataflash_bulk`), alternated call by call with the
  same-run baseline ``read via pymavlink`` (``DFReader_binary`` + ``recv_match``, the way
  before); both reported as median and min..max;
* ``diagnose --cal autopilot``: :func:`streamcal.inputs.autopilot_calibration` and
  :func:`streamcal.diagnose` against it, as shipped (candidate refits on the cell × time
  subsample of :mod:`streamcal.diagnosis.held.rank_subset`);
* ``CLI``: one ``streamcal diagnose LOG --cal autopilot`` process, imports included (once);
* the same with every candidate refitted on every sample (``rank_max`` = N: the way before);
* baseline: ``fit_core`` (hard_iron, soft_iron, coverage check off: a flight is a slice) on the
  same magnetometer samples, started from the autopilot calibration (stage 1 refuses a slice:
  its quadric is not an ellipsoid).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import SHARED, median_seconds, run_stamp  # noqa: E402

DEFAULT_LOG = SHARED / "data" / "real" / "flight" / "ardupilot_erle_PXFv2.0b_Rpi.BIN"
TARGET_S = 10.0


def _alternate_reads(log: str, repeats: int) -> tuple[list, list]:
    """Wall times (s) of the bulk read and the pymavlink read, alternated A, B, A, B."""
    from streamcal.inputs import read_recording
    from streamcal.inputs.dataflash import read_dataflash_pymavlink

    def pymav():
        read_dataflash_pymavlink(log)

    pymav()  # warm-up (imports pymavlink)
    bulk, base = [], []
    for _ in range(repeats):
        for fn, times in ((lambda: read_recording(log), bulk), (pymav, base)):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return bulk, base


def _cli_seconds(log: str) -> float:
    """Wall time (s) of one ``streamcal diagnose LOG --cal autopilot`` process (imports, read,
    diagnosis, report to a pipe): what a user waits for."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "streamcal", "diagnose", log, "--cal", "autopilot"],
                   cwd=root, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", default=str(DEFAULT_LOG))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    from streamcal.diagnosis.against import diagnose_against
    from streamcal.fitting.core import fit_core
    from streamcal.inputs import autopilot_calibration, read_recording

    print(run_stamp())
    track = read_recording(args.log)
    cal = autopilot_calibration(track)
    n = len(track.mag)
    span = float(track.t_mag[-1] - track.t_mag[0])
    t_read, t_pymav = _alternate_reads(args.log, args.repeats)
    out = {}

    def shipped():
        out["d"] = diagnose_against(track, autopilot_calibration(track))

    def every_sample():
        out["full"] = diagnose_against(track, cal, rank_max=n)

    t_diag = median_seconds(shipped, args.repeats)
    t_full = median_seconds(every_sample, max(1, args.repeats - 2), warmup=0)
    t_cli = _cli_seconds(args.log)
    t_fit = median_seconds(lambda: fit_core(track.mag, check_coverage=False, initial=cal), args.repeats)
    d, full = out["d"], out["full"]
    total = float(np.median(t_read)) + t_diag
    total_pymav = float(np.median(t_pymav)) + t_diag
    print(f"log {Path(args.log).name}: {n} MAG samples over {span:.0f} s")
    print(f"{'step':<52}{'s':>8}{'× plain fit':>13}")
    rows = [("read (DataFlash → Track, bulk decoder)", float(np.median(t_read))),
            ("read via pymavlink (same-run baseline)", float(np.median(t_pymav))),
            (f"diagnose --cal autopilot (refits on {d.held.n_ranked} of {n})", t_diag),
            ("read + diagnose", total),
            ("read via pymavlink + diagnose", total_pymav),
            ("CLI: streamcal diagnose LOG --cal autopilot (1 run)", t_cli),
            (f"diagnose, every refit on all {n} samples", t_full),
            ("baseline: plain fit_core, same samples, warm", t_fit)]
    for label, t in rows:
        print(f"{label:<52}{t:>8.2f}{t / t_fit:>13.2f}")
    print(f"read spread (min..max of {len(t_read)}): bulk {min(t_read):.3f}..{max(t_read):.3f} s, "
          f"pymavlink {min(t_pymav):.3f}..{max(t_pymav):.3f} s; bulk is "
          f"{np.median(t_pymav) / np.median(t_read):.1f}× faster")
    print(f"target read + diagnose ≤ {TARGET_S:.0f} s: {'met' if total <= TARGET_S else 'NOT met'}"
          f" ({total:.2f} s); subsample speed-up {t_full / t_diag:.2f}×")
    for label, dg in (("shipped", d), ("every sample", full)):
        top = dg.candidates[0] if dg.candidates else None
        print(f"{label:<14} rms {dg.rms:.4g} µT (sensor, {dg.n} samples)"
              + (f"; top {top.effect} {top.rms_before:.4g} → {top.rms_after:.4g} µT "
                 f"(significant {top.significant})" if top else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
