"""Benchmark of the attitude reference (docs/flight_logs.md): on the bundled flight logs and on
simulated vehicles with a known truth, the residual and heading error against the World
Magnetic Model rotated by the logged attitude, before (the calibration in force) and after
(the robust fit against it), the mounting found, and the time it takes.

    python tools/bench_attitude.py [--repeats 3]

Rows:

* each real log with attitude and a GPS position (the others say why not);
* the 2014 ArduPilot log with its readings turned by mounting rotations it was not flown with
  (the rotation must be found, the fit after it unchanged);
* simulated flights (soft iron, offsets, a motor current term, 0.3 µT noise) with several
  mountings: error of the fitted offsets and iron against the truth;
* a simulated rover and a still vehicle: ``fit --planar`` / ``fit --heading`` offsets against
  the truth;
* the time of one ``attitude_reference`` on a 1-hour 10 Hz simulated flight (median of
  ``--repeats``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import SHARED  # noqa: E402

FLIGHTS = SHARED / "data" / "real" / "flight"
S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])


def _row(name, out) -> str:
    a, o = out["attitude_reference"], out["orientation"] or {}
    if a["rms_uT_before"] is None:
        return f"{name:<44} no reference: {a['reason']}"
    h = a["heading_error_deg"]
    after = "  after —" if a["rms_uT_after"] is None else \
        f"{a['rms_uT_after']:>7.2f} µT {h['rms_after']:>6.2f}°"
    return (f"{name:<44} {a['rms_uT_before']:>7.2f} µT {h['rms_before']:>6.2f}° →{after}"
            f"  n {a['n']:>5} ({a['n_outliers']} out)  mount {o.get('name', '—')}")


def _turned(track, matrix):
    cols = dict(track.columns)
    mag = np.column_stack([cols[c] for c in ("mx", "my", "mz")])
    mag[track.mag_rows] = mag[track.mag_rows] @ matrix
    cols.update(zip(("mx", "my", "mz"), mag.T))
    return type(track)(cols, track.metadata)


def real_logs() -> None:
    from streamcal.fitting.attitude_reference import attitude_reference, calibration_in_force
    from streamcal.inputs.mount_rotations import by_name
    from streamcal.inputs import read_recording

    print("real logs: rms of f − e and heading error (rms), before → after")
    for path in sorted(FLIGHTS.glob("*")):
        if path.suffix.lower() not in (".bin", ".ulg"):
            continue
        track = read_recording(path)
        print(_row(path.name, attitude_reference(track, calibration_in_force(track))))
    track = read_recording(FLIGHTS / "ardupilot_erle_15-12-2014_16.BIN")
    for name in ("YAW_45", "YAW_90", "ROLL_180", "ROLL_270_YAW_135"):
        out = attitude_reference(_turned(track, by_name(name).matrix))
        print(_row(f"  16.BIN turned by {name}", out))


def simulated() -> None:
    from streamcal.fitting.attitude_reference import attitude_data
    from streamcal.inputs.mount_rotations import by_name
    from streamcal.fitting.no_tumble import fit_heading, fit_planar
    from streamcal.fitting.reference_fit import detect_rotation
    from streamcal.geomag import parse_date, wmm_field
    from streamcal.sim.flight import DATE, LAT, LON, simulated_log

    print("\nsimulated flights (truth: A = S_TRUE, b = 12,-7,20 µT, g = 0.2,-0.1,0.3 µT/A)")
    gain = np.array([0.2, -0.1, 0.3])
    for name in ("NONE", "YAW_45", "ROLL_180", "PITCH_90", "ROLL_90_YAW_135"):
        errs = []
        for seed in range(5):
            track, _ = simulated_log("flight", mount=by_name(name).matrix, S=S_TRUE,
                                     b_body=B_TRUE, current_gain=gain, seed=seed)
            data, _ = attitude_data(track)
            fit, _ = detect_rotation(data.m, data.expected,
                                     {"battery_current_a": data.cov["battery_current_a"]})
            # the fit's offset is at the median current a0: b + g a0
            b_at_zero = fit.b - fit.g["battery_current_a"] * fit.a0["battery_current_a"]
            errs.append((fit.rotation.name == name, np.abs(fit.A - S_TRUE).max(),
                         np.abs(b_at_zero - B_TRUE).max(),
                         np.abs(fit.g["battery_current_a"] - gain).max()))
        ok, da, db, dg = zip(*errs)
        print(f"  {name:<18} found {sum(ok)}/5  max |ΔA| {max(da):.4f}  max |Δb| {max(db):.3f} µT"
              f"  max |Δg| {max(dg):.4f} µT/A")
    ref = wmm_field(LAT, LON, 0.4, parse_date(DATE))
    planar_S = np.array([[1.05, 0.03, 0.0], [0.03, 0.97, 0.0], [0.0, 0.0, 1.0]])
    for turns in (2.0, 0.5):
        db = [np.abs(fit_planar(simulated_log("rover", S=planar_S, b_body=B_TRUE, seed=s,
                                              turns=turns)[0], ref).b - B_TRUE).max()
              for s in range(5)]
        print(f"  rover, {turns:g} turns: --planar max |Δb| {max(db):.3f} µT over 5 seeds")
    db = [np.abs(fit_heading(simulated_log("still", duration_s=10, heading_deg=h,
                                           b_body=B_TRUE, seed=s)[0], h, ref).b - B_TRUE).max()
          for s, h in enumerate((0, 45, 90, 200, 300))]
    print(f"  still, 10 s: --heading max |Δb| {max(db):.3f} µT over 5 headings")


def speed(repeats: int) -> None:
    from streamcal.fitting.attitude_reference import attitude_reference
    from streamcal.sim.flight import simulated_log

    track, _ = simulated_log("flight", duration_s=3600, current_gain=np.array([0.1, 0, 0]))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        attitude_reference(track, channels=["battery_current_a"])
        times.append(time.perf_counter() - t0)
    print(f"\n1-hour 10 Hz simulated flight ({len(track.t_mag)} samples): attitude_reference "
          f"median {np.median(times):.2f} s (min {min(times):.2f}, max {max(times):.2f})")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    if FLIGHTS.is_dir():
        real_logs()
    else:
        print(f"real logs: {FLIGHTS} not found (set STREAMCAL_SHARED)")
    simulated()
    speed(args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
