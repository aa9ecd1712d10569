#!/usr/bin/env python3
"""Replay every real track through the streaming calibrator and compare with the batch fit.

For each track in ``data/real/tracks`` under ``STREAMCAL_SHARED``: the streaming calibrator
(synchronous fits, so the result is reproducible; blocks of 100 rows; covariates ``temp`` and aux
channels kept) is fed the whole track, and its final calibration is compared with
:func:`streamcal.fitting.fit` on the whole track by the normalized model deviation of the paper
(eq. 40, ``Calibration.model_error``). When ``fit`` refuses the track for lack of coverage, the
comparison is with ``fit(..., check_coverage=False)`` and the table says so.

Then the environment-change scenarios (``tests/test_stream_environment.py``): BROAD 32 with a
magnet on the board for t ∈ [34, 100] s (with BROAD 02's calibration in the state directory, and
from scratch: the replay's closing words and a batch fit of each environment alone), and sunsided
set 1 → set 2 through one calibrator.

    python tools/replay_real_tracks.py [-o results/replay_real_tracks.md]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _bench_common import REAL_TRACKS, REPO, run_stamp

sys.path.insert(0, str(REPO))

from streamcal.samples import SampleBlock  # noqa: E402
from streamcal.errors import StreamcalError  # noqa: E402
from streamcal.fitting import fit  # noqa: E402
from streamcal.stream import CalibrationStore, CoverageBuffer, StreamingCalibrator  # noqa: E402
from streamcal.stream.coverage import percent  # noqa: E402
from streamcal.stream.guard import holdout_error  # noqa: E402
from streamcal.inputs.track import Track  # noqa: E402

BLOCK = 100


def stream(tracks, shifts=None, store=None) -> tuple[StreamingCalibrator, dict, list, float]:
    """Replay ``tracks`` (one after the other, times shifted by ``shifts``) through one
    calibrator; returns it, the event counts, the notable events and the wall time (s)."""
    shifts = shifts or [0.0] * len(tracks)
    first = tracks[0]
    covariates = tuple(n for n in ("temp", *first.aux_names) if first.has(n))
    sc = StreamingCalibrator(synchronous=True, unit=first.mag_unit, store=store,
                             buffer=CoverageBuffer(covariates=covariates))
    counts, notable = {}, []
    start = time.perf_counter()
    for track, shift in zip(tracks, shifts):
        for b in track.blocks(BLOCK):
            if shift:
                b = SampleBlock(t=b.t + shift, mag=b.mag, accel=b.accel, gyro=b.gyro,
                                temp=b.temp, aux=b.aux)
            for e in sc.ingest(b):
                counts[e.kind] = counts.get(e.kind, 0) + 1
                notable.append(e)
    for e in sc.close():
        counts[e.kind] = counts.get(e.kind, 0) + 1
        notable.append(e)
    wall = time.perf_counter() - start
    return sc, counts, [e for e in notable if e.kind not in ("coverage", "stored")], wall


def batch(track):
    """``(calibration, note)``: fit on the whole track, or without the coverage check."""
    try:
        return fit(track), "fit"
    except StreamcalError as exc:
        reason = str(exc).split(":")[0].split(".")[0][:90]
        try:
            return fit(track, check_coverage=False), f"refused ({reason}); check_coverage=False"
        except StreamcalError as exc2:
            return None, f"refused ({reason}); also without the coverage check: {str(exc2)[:80]}"


def per_track(paths) -> list[dict]:
    rows = []
    for path in paths:
        track = Track.read(path)
        sc, counts, _, wall = stream([track])
        ref, note = batch(track)
        cal = sc.calibration
        row = {"name": path.name.split(".")[0], "n": int(track.mag_rows.sum()),
               "unit": track.mag_unit.split(" ")[0], "wall": wall, "counts": counts,
               "coverage": sc.buffer.measured_fraction, "batch": note, "cal": cal, "ref": ref}
        if cal is not None and ref is not None:
            row["dev"] = cal.model_error(ref)
            m = track.mag
            row["err_stream"] = holdout_error(cal, m)
            row["err_batch"] = holdout_error(ref, m)
        rows.append(row)
        print(f"{row['name']:40s} dev {row.get('dev', float('nan')):.4f}  {note}", flush=True)
    return rows


def broad32(tracks_dir) -> list[str]:
    before = fit(Track.read(tracks_dir / "broad_02_undisturbed_slow_rotation_B.csv.gz"))
    track = Track.read(tracks_dir / "broad_32_attached_magnet_1cm.csv.gz")
    with tempfile.TemporaryDirectory() as d:
        CalibrationStore(d).save(before)
        sc, counts, events, wall = stream([track], store=CalibrationStore(d))
    lines = [f"Events (replay {wall:.1f} s wall): {_counts(counts)}", ""]
    lines += [f"- t = {e.t:.2f} s, `{e.kind}`: {e.message}" for e in events if e.t is not None]
    m_after = track.mag[track.t_mag >= 105.0]
    lines += ["", f"Final calibration vs the pre-magnet one (BROAD 02 fit): deviation "
              f"{sc.calibration.model_error(before):.4f}; stale: {sc.stale}; mean radial error on "
              f"t ≥ 105 s: {holdout_error(sc.calibration, m_after):.3f} µT (pre-magnet calibration: "
              f"{holdout_error(before, m_after):.3f} µT)."]
    return lines


def broad32_from_scratch(tracks_dir) -> list[str]:
    """``streamcal replay`` of BROAD 32 with no state: its closing words, and what a batch fit
    makes of each environment alone (magnet on for t ∈ [34, 100] s)."""
    import contextlib
    import io
    import json

    from streamcal.cli import main as cli

    path = tracks_dir / "broad_32_attached_magnet_1cm.csv.gz"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = cli(["replay", str(path), "--sync-fits", "--block", str(BLOCK), "--json"])
    summary = json.loads(out.getvalue().splitlines()[-1])
    lines = [f"`streamcal replay {path.name} --sync-fits` (no state) exits {code}; "
             f"{summary['fits']} fits ({summary['accepted']} accepted, {summary['rejected']} "
             f"rejected, {summary['failed']} failed), {summary['drift']} drift. Its closing words:",
             "", f"> no calibration: {summary.get('why', '—')}", "",
             "Each environment alone, by the batch fit (magnet times from the recording's notes):",
             ""]
    track = Track.read(path)
    t, m = track.t_mag, track.mag
    for lo, hi, what in ((0.0, 34.0, "before the magnet (board at rest)"),
                         (34.0, 100.0, "magnet on the board"),
                         (100.0, float("inf"), "after the magnet")):
        sel = (t >= lo) & (t < hi)
        try:
            cal = fit(m[sel])
            verdict = f"fit accepted, rms {cal.rms:.3g} µT"
        except StreamcalError as exc:
            verdict = f"refused: {str(exc).split('. ')[0][:150]}"
        lines.append(f"- t ∈ [{lo:g}, {hi:g}) s, {what}, {int(sel.sum())} samples: {verdict}")
    return lines


def sunsided(tracks_dir) -> list[str]:
    s1 = Track.read(tracks_dir / "sunsided_set1_tiltsphere.csv.gz")
    s2 = Track.read(tracks_dir / "sunsided_set2_fullsphere.csv.gz")
    shift = float(s1.t[-1]) + 10.0
    sc, counts, events, wall = stream([s1, s2], [0.0, shift])
    ref1, ref2 = fit(s1), fit(s2)
    lines = [f"Set 2 starts at t = {shift:.2f} s. Events (replay {wall:.1f} s wall): "
             f"{_counts(counts)}", ""]
    lines += [f"- t = {e.t:.2f} s, `{e.kind}`: {e.message}" for e in events
              if e.kind in ("drift", "forgot", "recalled", "rejected", "fit_failed", "discarded",
                            "disturbance")
              or (e.kind == "accepted" and abs(e.t - shift) < 80)]
    lines += ["", f"Final calibration vs fit(set 2): deviation {sc.calibration.model_error(ref2):.4f}; "
              f"vs fit(set 1): {sc.calibration.model_error(ref1):.4f}; fit(set 1) vs fit(set 2): "
              f"{ref1.model_error(ref2):.4f} (‖Δb‖ = {np.linalg.norm(ref1.b - ref2.b):.1f} µT)."]
    return lines


def _counts(counts: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))


def table(rows) -> list[str]:
    out = ["| track | mag samples | unit | fits (acc/rej/fail) | drift | disturbances | coverage "
           "| batch reference | deviation eq. 40 | radial error stream / batch | replay wall |",
           "|---|---:|---|---|---:|---:|---:|---|---:|---|---:|"]
    for r in rows:
        c = r["counts"]
        fits = f"{c.get('fit_started', 0)} ({c.get('accepted', 0)}/{c.get('rejected', 0)}/" \
               f"{c.get('fit_failed', 0)})"
        if r["cal"] is None:
            dev, err = "no streaming calibration", "—"
        elif r["ref"] is None:
            dev, err = "no batch reference", "—"
        else:
            dev = f"{r['dev']:.4f}"
            err = f"{r['err_stream']:.3g} / {r['err_batch']:.3g}"
        out.append(f"| {r['name']} | {r['n']} | {r['unit']} | {fits} | {c.get('drift', 0)} | "
                   f"{c.get('disturbance', 0)} | {percent(r['coverage'])} | {r['batch']} | {dev} | {err} | "
                   f"{r['wall']:.2f} s |")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", default=str(REPO / "results" / "replay_real_tracks.md"))
    p.add_argument("--tracks", default=str(REAL_TRACKS))
    args = p.parse_args()
    tracks_dir = Path(args.tracks)
    paths = sorted(p for p in tracks_dir.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    rows = per_track(paths)
    text = ["# Streaming calibrator on the real tracks", "", "```", run_stamp(), "```", "",
            "Each track is replayed through `StreamingCalibrator` (synchronous fits, blocks of "
            f"{BLOCK} rows) and its final calibration is compared with `streamcal.fitting.fit` on "
            "the whole track: deviation = ‖[K b] − [K' b']‖_F / ‖[K' b']‖_F (paper eq. 40). "
            "Radial error: mean of |‖K⁻¹(m − b)‖ − 1|·radius over all samples after dropping the "
            "largest 10 % (sensor unit), for the streaming and the batch calibration.", ""]
    text += table(rows)
    text += ["", "## BROAD 32: magnet on the board for t ∈ [34, 100] s", "",
             "The state directory starts with the calibration of BROAD 02 (same sensor, "
             "undisturbed), as a daemon's would.", ""]
    text += broad32(tracks_dir)
    text += ["", "## BROAD 32 from scratch (no state)", ""]
    text += broad32_from_scratch(tracks_dir)
    text += ["", "## sunsided set 1 → set 2 through one calibrator", ""]
    text += sunsided(tracks_dir)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    from streamcal.atomic import atomic_write_text

    atomic_write_text(args.output, "\n".join(text) + "\n")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
