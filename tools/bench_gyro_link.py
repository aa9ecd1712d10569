"""The gyro link measured against holding (issue #10): simulated slices and the real flight logs.

    python3 tools/bench_gyro_link.py [--seeds N] [--flights | --guard]

Simulated (:func:`streamcal.sim.yaw_slice.yaw_slice`, a yaw-turning slice tilting ±25°,
120 s, 100 Hz, true K and b fixed): the given calibration has K_zz 1 µT too large and is
otherwise exact. The sphere holds K_zz (it trades against b_z on such a slice) and bends b_z
to match. Per seed and reading noise, the error of K_zz and b_z after the diagnosis against the
calibration (``streamcal.diagnose(track, calibration=cal)``) with the gyro link (as shipped)
and with it switched off (the track's gyro columns removed): held vs gyro.

``--flights``: each ArduPilot log of data/real/flight (under STREAMCAL_SHARED) against its autopilot
calibration: what the gyro link did (``gyro_link`` of the diagnosis) and the time it took,
beside the same diagnosis without gyro columns, in the same run.

``--guard``: the guard of :mod:`streamcal.diagnosis.held.gyro_guard` on and off on three slices
(every offset 2 µT off over 120 s at σ 0.4 µT — the case it was built for —, the same over
300 s at σ 0.15 µT, and K_zz 1 µT off): what is pinned and its error from the truth in σ.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from _bench_common import REAL_FLIGHTS
import streamcal
from streamcal.calibration import Calibration
from streamcal.inputs.track import Track
from streamcal.sim.yaw_slice import yaw_slice

K = np.array([[47.0, 1.2, -0.8], [0.0, 49.0, 0.6], [0.0, 0.0, 46.5]])
B = np.array([12.0, -7.0, 20.0])
FLIGHT = REAL_FLIGHTS


def without_gyro(track: Track) -> Track:
    """The same track without the gyro columns: the gyro link is then not tried."""
    cols = {c: v for c, v in track.columns.items() if c not in ("gx", "gy", "gz")}
    return Track(cols, track.metadata)


def simulated(seeds, noises):
    print("| noise µT | seed | held K_zz err | gyro K_zz err ± σ | held b_z err | gyro b_z err "
          "| pinned | reason |")
    print("|---|---|---|---|---|---|---|---|")
    Kg = K.copy()
    Kg[2, 2] += 1.0
    for noise in noises:
        for seed in seeds:
            res = yaw_slice(120, seed=seed, K=K, b=B, tilt_deg=25, noise_uT=noise)
            cal = Calibration(K=Kg, b=B.copy(), model=("hard_iron", "soft_iron"))
            out = {}
            for label, track in (("held", without_gyro(res.track)), ("gyro", res.track)):
                d = streamcal.diagnose(track, calibration=cal, candidates=[], ladder=False)
                out[label] = d
            h, g = out["held"], out["gyro"]
            sd = g.held.gyro_pinned.get("K_zz", {}).get("sigma", float("nan"))
            print(f"| {noise:g} | {seed} | {h.calibration.K[2, 2] - K[2, 2]:+.3f} "
                  f"| {g.calibration.K[2, 2] - K[2, 2]:+.3f} ± {sd:.3f} "
                  f"| {h.calibration.b[2] - B[2]:+.3f} | {g.calibration.b[2] - B[2]:+.3f} "
                  f"| {', '.join(g.held.gyro_pinned) or '—'} "
                  f"| {g.held.gyro_link.get('reason', '')[:60]} |")


def guard(seeds):
    """The guard (streamcal/diagnosis/held/gyro_guard.py) on and off (P_GUARD = 0: never refuses):
    what is pinned, its error from the truth in σ, and the guard's shift and p."""
    from streamcal.diagnosis import gyro_guard

    truth = {"K_xy": K[0, 1], "K_xz": K[0, 2], "K_yy": K[1, 1], "K_yz": K[1, 2],
             "K_zz": K[2, 2], "b_x": B[0], "b_y": B[1], "b_z": B[2]}
    Kg = K.copy()
    Kg[2, 2] += 1.0
    cases = {"offsets +2, 120 s σ 0.4 (misleading)": dict(duration=120, tilt=15, yaw=30,
                                                        noise=0.4, K=K, b=B + 2.0),
             "offsets +2, 300 s σ 0.15": dict(duration=300, tilt=15, yaw=30, noise=0.15,
                                              K=K, b=B + 2.0),
             "K_zz +1, 120 s σ 0.15": dict(duration=120, tilt=25, yaw=None, noise=0.15, K=Kg,
                                           b=B)}
    print("| case | seed | guard | pinned (error from truth, σ) | guard shift | p | reason |")
    print("|---|---|---|---|---|---|---|")
    p_guard = gyro_guard.P_GUARD
    for label, c in cases.items():
        for seed in seeds:
            res = yaw_slice(c["duration"], seed=seed, K=K, b=B, tilt_deg=c["tilt"],
                            yaw_deg=c["yaw"], noise_uT=c["noise"])
            cal = Calibration(K=c["K"].copy(), b=c["b"].copy(),
                              model=("hard_iron", "soft_iron"))
            for on in (False, True):
                gyro_guard.P_GUARD = p_guard if on else 0.0
                d = streamcal.diagnose(res.track, calibration=cal, candidates=[], ladder=False)
                link, g = d.held.gyro_link, d.held.gyro_link.get("guard", {})
                pinned = ", ".join(f"{k} {v['value'] - truth[k]:+.2f} ± {v['sigma']:.2f} "
                                   f"({(v['value'] - truth[k]) / v['sigma']:+.1f} σ)"
                                   for k, v in d.held.gyro_pinned.items()) or "—"
                shift = ", ".join(f"{k} {v:+.2f}" for k, v in g.get("shift", {}).items()) or "—"
                print(f"| {label} | {seed} | {'on' if on else 'off'} | {pinned} | {shift} "
                      f"| {g.get('p_value', float('nan')):.2g} | {link['reason'][:50]} |")
    gyro_guard.P_GUARD = p_guard


def flights():
    from streamcal.inputs import autopilot_calibration, read_recording

    for path in sorted(FLIGHT.glob("ardupilot_*.BIN")):
        track = read_recording(path)
        cal = autopilot_calibration(track)
        times = {"gyro": [], "no gyro": []}
        result = None
        for _ in range(2):   # alternate A, B, A, B
            for label, tr in (("gyro", track), ("no gyro", without_gyro(track))):
                t0 = time.perf_counter()
                d = streamcal.diagnose(tr, calibration=cal, calibration_source="autopilot")
                times[label].append(time.perf_counter() - t0)
                if label == "gyro":
                    result = d
        link = result.held.gyro_link
        est = {k: (round(v.get("value", np.nan), 3), round(v.get("sigma", v.get(
            "sigma_predicted", np.nan)), 3)) for k, v in link.get("estimates", {}).items()}
        print(f"{path.name}: held {result.held.parameters}; pinned {result.held.gyro_pinned}; used "
              f"{link['used']}: {link['reason']}")
        print(f"  link rms {link.get('rms_held', float('nan')):.4g} vs no-rotation "
              f"{link.get('rms_still', float('nan')):.4g} ({result.unit}); estimates {est}")
        print(f"  diagnose time median {np.median(times['gyro']):.2f} s (runs "
              f"{', '.join(f'{v:.2f}' for v in times['gyro'])}) vs without gyro "
              f"{np.median(times['no gyro']):.2f} s "
              f"({', '.join(f'{v:.2f}' for v in times['no gyro'])})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--flights", action="store_true")
    ap.add_argument("--guard", action="store_true", help="only the guard on and off")
    args = ap.parse_args()
    if args.guard:
        guard(range(1, args.seeds + 1))
        return
    simulated(range(1, args.seeds + 1), (0.15, 0.4))
    if args.flights:
        flights()


if __name__ == "__main__":
    main()
