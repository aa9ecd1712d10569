"""Benchmark: motor compensation checked on samples it was not fitted on
(:func:`streamcal.export.motor_check.held_out_check`, docs/flight_logs.md).

    python tools/bench_motor_holdout.py [--fraction 0.5]

Each flight is split in time at its median magnetometer sample. On one part the calibration in
force is refined with a motor term on the channel an autopilot compensates (``fit --cal
autopilot --add aux_interference=CHANNEL``) and, as a control, without it; each is exported as
ArduPilot and PX4 parameters and applied with that firmware's formula to the other part. Rows
per direction (fitted on the first part, then on the last):

* ``in force``: the calibration in the log's parameters, the same-run baseline;
* ``refit``: refined on the fitted part without a motor term;
* ``+motor``: refined with it (ArduPilot's formula; PX4's gives the same figures, ``=px4``
  says when they agree to 0.002).

Columns: field-magnitude spread on the held-out part (std / mean and 1.4826·MAD / median, %);
heading error against the attitude reference (rms, 95th percentile, degrees) where the log
has attitude and GPS (its caveat: the logged yaw is itself steered by the compass); the fitted
term's size at one channel unit (µT at full throttle, µT per A); the heading of streamcal's
own correction of the ``+motor`` calibration (the firmwares' symmetric matrix drops the rotation
a refit of the iron turns its frame by). Logs: the bundled ArduPilot
flights with a throttle or current channel, and a simulated flight with attitude, GPS and a
motor current term of 0.37 µT/A (the truth).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_common import REAL_FLIGHTS, run_stamp  # noqa: E402

LOGS = ("ardupilot_erle_PXFv2.0b_Rpi.BIN", "ardupilot_erle_Erle-Brain3.BIN",
        "ardupilot_erle_15-12-2014_16.BIN")
CHANNELS = ("throttle", "battery_current_a")
S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])
GAIN = np.array([0.2, -0.1, 0.3])


def _cell(v) -> str:
    return "" if v is None else f"{v:.3f}"


def _rows(label: str, out: dict) -> list[str]:
    size = float(np.linalg.norm(out["g_uT"]))
    own = out["streamcal"].get("heading_rms_deg")
    lines = []
    for name, title in (("before", "in force"), ("refit", "refit"), ("after", "+motor")):
        ap, px4 = out[name]["ardupilot"], out[name]["px4"]
        agree = all(abs(ap[k] - px4[k]) <= 2e-3 for k in ap)
        lines.append(f"| {label} | {out['channel']} | {out['fit_on']} | {title} | "
                     f"{_cell(ap['spread_pct'])} | {_cell(ap['spread_robust_pct'])} | "
                     f"{_cell(ap.get('heading_rms_deg'))} | {_cell(ap.get('heading_p95_deg'))} | "
                     f"{'=px4' if agree else 'px4 differs'} | "
                     f"{f'{size:.2f}' if name == 'after' else ''} | "
                     f"{_cell(own) if name == 'after' else ''} |")
    return lines


def _simulated():
    from streamcal.inputs.autopilot_cal import calibration_from_ardupilot
    from streamcal.sim.flight import simulated_log

    track, truth = simulated_log("flight", S=S_TRUE, b_body=B_TRUE, current_gain=GAIN, seed=5)
    S_ap = np.linalg.inv(S_TRUE)
    params = {f"COMPASS_OFS_{a}": -10.0 * B_TRUE[k] for k, a in enumerate("XYZ")}
    params.update({f"COMPASS_DIA_{a}": S_ap[k, k] for k, a in enumerate("XYZ")})
    params.update(COMPASS_ODI_X=S_ap[0, 1], COMPASS_ODI_Y=S_ap[0, 2], COMPASS_ODI_Z=S_ap[1, 2])
    cal = calibration_from_ardupilot(params, float(np.linalg.norm(truth["b_ned"])),
                                     source="simulated COMPASS_* without the motor term")
    return track, cal


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fraction", type=float, default=0.5,
                   help="share of the magnetometer samples in the first part (default 0.5)")
    args = p.parse_args(argv)
    from streamcal.export.motor_check import held_out_check
    from streamcal.inputs import autopilot_calibration, read_recording

    print(run_stamp(argv))
    print()
    print("| log | channel | fitted on | calibration | spread % | robust spread % | "
          "heading rms ° | heading p95 ° | PX4 formula | term µT/unit | streamcal's own "
          "heading rms ° |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    notes = []
    cases = []
    for name in LOGS:
        path = REAL_FLIGHTS / name
        if not path.exists():
            notes.append(f"{name}: not found under {REAL_FLIGHTS}")
            continue
        track = read_recording(path)
        cases += [(name, track, autopilot_calibration(track), ch)
                  for ch in CHANNELS if ch in track.aux_names]
    track, cal = _simulated()
    cases.append(("simulated flight (0.37 µT/A)", track, cal, "battery_current_a"))
    for label, track, cal, channel in cases:
        for fit_on in ("first", "last"):
            out = held_out_check(track, cal, channel, fraction=args.fraction, fit_on=fit_on)
            print("\n".join(_rows(label, out)))
            if "heading" in out and fit_on == "first":
                notes.append(f"{label}: {out['heading']}")
    for note in dict.fromkeys(notes):
        print(f"\n{note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
