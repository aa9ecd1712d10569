"""Benchmark of every compass of a flight log (issue #24 item 1): reading, comparing, diagnosing.

    python tools/bench_compasses.py [--seconds 300] [--repeats 3]

On a self-made three-compass DataFlash log (tests/_dataflash_log.py: a tumble of ``--seconds``,
MAG/MAG2/MAG3 at 10 Hz, compass 1 with 150 mG of hard iron its calibration misses, compass 2
right) and on the bundled real flight logs, timed as the median of ``--repeats`` after a warm-up:

* ``read every compass``: :func:`streamcal.inputs.read_compasses` (the log parsed once), beside
  the same-run baseline of one :func:`read_recording` per compass (parsed once per compass);
* ``consistency``: :func:`streamcal.diagnosis.compass_consistency.compare_all` over the three
  pairs under the autopilot's calibrations;
* ``diagnose each``: :func:`streamcal.diagnose` once per compass (what ``--compass all`` adds).

Accuracy, against the log's truth: the median 3-D angle of each pair under the autopilot's
calibration beside the angle between the noise-free logged fields (f vs f + 150 mG on x); the
3 mG noise of each compass alone gives about 0.5° between two right compasses.

Measured (2026-11-27, 2 CPUs, 300 s): read every compass 0.10 s vs 0.13 s for one read per
compass; consistency of 3 pairs × 3000 samples 19 ms; diagnose each compass 9.3 s; pair 0–1
median 14.72° (truth 14.76°), pair 0–2 0.58° (noise only).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
from _bench_common import SHARED, median_seconds, run_stamp  # noqa: E402
from tests._dataflash_log import write_flight  # noqa: E402

ERR = np.array([150.0, 0.0, 0.0])


def _angle(u, v):
    c = np.sum(u * v, 1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def _fields(tracks):
    from streamcal.diagnosis.compass_consistency import compass_field
    from streamcal.inputs import autopilot_calibration

    return [compass_field(t, autopilot_calibration(t), int(t.metadata["compass_instance"]),
                          float(t.metadata["log_t0_s"])) for t in tracks]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    from streamcal.diagnosis import diagnose
    from streamcal.diagnosis.compass_consistency import compare_all
    from streamcal.inputs import read_compasses, read_recording

    print(run_stamp(argv))
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "three.bin"
        truth = write_flight(log, [{"ofs": (30, -20, 10)}, {"ofs": (-50, 40, 5), "err": ERR},
                                   {"ofs": (12, 7, -30)}], seconds=args.seconds)
        size = log.stat().st_size
        once = median_seconds(lambda: read_compasses(log), args.repeats)
        each = median_seconds(lambda: [read_recording(log, compass=k) for k in range(3)],
                              args.repeats)
        tracks = read_compasses(log)
        fields = _fields(tracks)
        cmp_s = median_seconds(lambda: compare_all(fields, "autopilot"), args.repeats)
        diag_s = median_seconds(lambda: [diagnose(t) for t in tracks], 1, warmup=0)
        pairs = [p.to_dict() for p in compare_all(fields, "autopilot")]
    n = len(tracks[0].t_mag)
    print(f"self-made log: {args.seconds:g} s, 3 compasses x {n} MAG samples, {size / 1e6:.2f} MB")
    print(f"  read every compass (parsed once)   {once:8.3f} s")
    print(f"  baseline: one read per compass     {each:8.3f} s   ({each / once:.2f}x)")
    print(f"  consistency, 3 pairs               {cmp_s * 1e3:8.1f} ms")
    print(f"  diagnose each compass              {diag_s:8.2f} s")
    f = truth["field"]
    expected = {(0, 1): _angle(f, f + ERR), (0, 2): np.zeros(len(f)), (1, 2): _angle(f + ERR, f)}
    for p in pairs:
        want = float(np.median(expected[(p["a"], p["b"])]))
        print(f"  pair {p['a']}-{p['b']}: median angle {p['angle_deg_median']:.3f} deg "
              f"(truth {want:.3f}), inconsistent {p['fraction_inconsistent']:.4f}")
    flight = SHARED / "data" / "real" / "flight"
    for name in sorted(flight.glob("*.BIN")) + sorted(flight.glob("*.ulg")):
        t_all = median_seconds(lambda: read_compasses(name), args.repeats)
        count = len(read_compasses(name))
        t_one = median_seconds(lambda: read_recording(name), args.repeats)
        print(f"{name.name}: {count} compass(es); read every compass {t_all:.3f} s, "
              f"default compass alone {t_one:.3f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
