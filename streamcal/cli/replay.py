"""``streamcal replay TRACK``: run the streaming pipeline over a recorded track (docs/cli.md).

Feeds the track to :class:`~streamcal.stream.StreamingCalibrator` block by block, as a device
would (``--realtime`` keeps the track's pace), prints the events — coverage milestones, fits,
acceptances and rejections with their reasons, drift — and a final summary, and leaves the state
directory as the daemon would.
"""
from __future__ import annotations

import itertools
import json
import math
import re
import sys
import time

import numpy as np

from ..calibration import DEFAULT_MODEL, jsonable
from ..stream.coverage import coverage_words, percent
from ._common import RECORDING_HELP, add_input_options, recording_chunks

#: Relative spread about one fitted sphere beyond which the samples are probably not one
#: environment's: soft iron leaves 1.7–6.4 % on the real one-environment tracks, BROAD 32 (a
#: magnet on the board for half of it) 9 %.
_ONE_SPHERE = 0.08
#: Rows per chunk read from the track file (about 1 MB of text; 50 000 rows peaked 60 MiB higher).
_CHUNK_ROWS = 10_000


def register(sub) -> None:
    p = sub.add_parser("replay", help="run the streaming calibrator over a recorded track",
                       description="Replay a recorded track through the streaming pipeline "
                                   "(coverage buffer, recalibration policy, background fits, "
                                   "acceptance guard, calibration store) and print its events.")
    p.add_argument("track", help=RECORDING_HELP)
    add_input_options(p, skip_bad_rows=True)
    p.add_argument("--realtime", action="store_true", help="sleep to follow the track's time")
    p.add_argument("--state-dir", metavar="DIR",
                   help="keep calibration.json and its history here, as the daemon does")
    p.add_argument("--json", action="store_true", help="one JSON object per event line")
    p.add_argument("--block", type=int, default=50, metavar="N",
                   help="rows per block fed to the calibrator (default: %(default)s)")
    p.add_argument("--model", default=",".join(DEFAULT_MODEL),
                   help="comma-separated effects fitted by the background fits "
                        "(default: %(default)s)")
    p.add_argument("--async-fits", action="store_true",
                   help="run fits on a worker thread while samples keep coming, as the daemon "
                        "does (the output then depends on how fast the fits run); default "
                        "without --realtime: each fit runs when it is due, so a replay is "
                        "reproducible")
    p.add_argument("--sync-fits", action="store_true",
                   help="run each fit when it is due, also with --realtime (the default "
                        "without --realtime)")
    from .daemon import add_http_options

    add_http_options(p, "with --realtime: ")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from ..errors import InputError
    from ..stream import CalibrationStore, CoverageBuffer, StreamingCalibrator
    from ..inputs.chunks import iter_track_blocks

    from ._location import location_reference

    if args.block < 1:
        raise InputError(f"--block: must be a positive number of rows, got {args.block}")
    location_reference(args)    # a mistyped --lat/--date said before the reading
    model = tuple(m.strip() for m in args.model.split(",") if m.strip())
    # section-1 tracks are read in chunks (memory bounded by a chunk, not the recording's
    # length); other formats are read whole by their libraries
    chunks = recording_chunks(args, rows=_CHUNK_ROWS)
    track = next(chunks)       # the first chunk: the file's columns and metadata
    covariates = tuple(n for n in ("temp", *track.aux_names) if track.has(n))
    store = CalibrationStore(args.state_dir) if args.state_dir else None
    calibrator = StreamingCalibrator(store=store, model=model, unit=track.mag_unit,
                                     buffer=CoverageBuffer(covariates=covariates),
                                     synchronous=_synchronous(args))
    emit = _printer(args.json)
    counts: dict[str, int] = {}
    refusals: dict[str, int] = {}        # why fits failed or candidates were rejected
    bar = tqdm(total=None, unit="row", file=sys.stderr, dynamic_ncols=True,
               disable=args.json or not sys.stderr.isatty(), desc="replay")
    start_wall, start_t = time.monotonic(), None
    from .daemon import replay_page

    page = replay_page(args, calibrator)
    finished = False
    try:
        for block in iter_track_blocks(itertools.chain([track], chunks), args.block):
            start_t = float(block.t[0]) if start_t is None else start_t
            if args.realtime:
                delay = start_wall + (float(block.t[-1]) - start_t) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            events = calibrator.ingest(block)
            if page is not None:
                page.observe(block, events)
            for event in events:
                counts[event.kind] = counts.get(event.kind, 0) + 1
                _note_refusal(event, refusals)
                emit(event, bar)
                if event.kind == "coverage" and not args.json:
                    _show_coverage(calibrator, event, bar)
            bar.update(len(block))
        for event in calibrator.close():
            counts[event.kind] = counts.get(event.kind, 0) + 1
            _note_refusal(event, refusals)
            emit(event, bar)
        finished = True
    finally:
        bar.close()
        if page is not None:
            page.close(finished)
    if not calibrator.n_ingested:
        if page is not None:
            page.observers[0].close_page()
        raise InputError(f"{args.track}: no magnetometer rows (mx,my,mz) to calibrate from")
    summary = _summary(calibrator, counts, track, args)
    if calibrator.calibration is None:
        summary["why"] = _why_none(calibrator, refusals, _mag_sample(args, calibrator.n_ingested))
    if args.json:
        print(json.dumps(jsonable(summary), allow_nan=False))
    else:
        print(summary["message"])
    if calibrator.calibration is None:
        print(f"streamcal replay: no calibration: {summary['why']}; {summary['hint']}",
              file=sys.stderr)
    if page is not None:
        from ._live_replay import serve_after_replay

        serve_after_replay(page, "replay", None, start_wall)
    return 1 if calibrator.calibration is None else 0


def _synchronous(args) -> bool:
    """Fits run when they are due (reproducible) unless the replay follows the track's pace
    (``--realtime``) or ``--async-fits`` asks for the daemon's worker thread."""
    if args.sync_fits and args.async_fits:
        from ..errors import InputError

        raise InputError("--sync-fits and --async-fits: choose one")
    return args.sync_fits or not (args.realtime or args.async_fits)


def _mag_sample(args, n: int, most: int = 200_000):
    """The track's ``n`` magnetometer samples (n,3), or every k-th (k = ⌈n / most⌉) — read in
    a second pass over the file so that memory stays bounded."""
    step, seen, parts = max(1, -(-n // most)), 0, []
    for chunk in recording_chunks(args, rows=_CHUNK_ROWS):
        m = chunk.mag
        parts.append(m[(-seen) % step::step])
        seen += len(m)
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def _printer(as_json: bool):
    def emit(event, bar):
        if as_json:
            line = json.dumps(jsonable(event.to_dict()), allow_nan=False)
        else:
            when = f"{event.t:9.2f} s" if event.t is not None and math.isfinite(event.t) else " " * 11
            line = f"[{when}] {event.kind:<12} {event.message}"
        if bar.disable:
            print(line, flush=True)
        else:
            bar.write(line, file=sys.stdout)
    return emit


def _show_coverage(calibrator, event, bar) -> None:
    """The terminal map of the sphere (which parts are still empty) at a coverage milestone:
    the coverage ``event``'s own figures and cells (a fit accepted in the same stage reframes
    the buffer, and its coverage then differs)."""
    from ..report.terminal import coverage_view

    report = event.detail
    view = coverage_view(calibrator.buffer, report,
                         occupied=None if report is None else report.occupied)
    if bar.disable:
        print(view, flush=True)
    else:
        bar.write(view, file=sys.stdout)


def _summary(calibrator, counts, track, args) -> dict:
    cal = calibrator.calibration
    report = calibrator.coverage
    out = {"event": "summary", "samples": calibrator.n_ingested,
           "fits": counts.get("fit_started", 0), "accepted": counts.get("accepted", 0),
           "rejected": counts.get("rejected", 0), "failed": counts.get("fit_failed", 0),
           "drift": counts.get("drift", 0), "disturbances": counts.get("disturbance", 0),
           "environments": calibrator.environment_summary(),
           "coverage": round(report.fraction, 4) if report.measured else None,
           "hint": report.hint, "state_dir": args.state_dir}
    if cal is not None:
        out.update({"K": cal.K.tolist(), "b": cal.b.tolist(),
                    "rms": float(cal.rms) if math.isfinite(cal.rms) else None, "unit": cal.unit})
        from ..units import display_unit, with_unit

        result = (f"calibration rms {with_unit(f'{cal.rms:.3g}', cal.unit)}, b = "
                  f"{with_unit(str(np.round(cal.b, 2).tolist()), cal.unit)}"
                  + ("" if display_unit(cal.unit) else " (unit unknown)"))
    else:
        result = "no calibration accepted"
    out["message"] = (f"replayed {calibrator.n_ingested} magnetometer samples of {args.track}: "
                      f"{out['fits']} fits, {out['accepted']} accepted, {out['rejected']} rejected, "
                      f"{out['failed']} failed, {out['drift']} drift, "
                      f"{out['disturbances']} transient disturbances; "
                      f"{coverage_words(out['coverage'])}; {result}"
                      + (f"; state in {args.state_dir}" if args.state_dir else ""))
    return out


def _note_refusal(event, refusals: dict) -> None:
    """Count why fits failed (the fit's message) and candidates were rejected (the rule)."""
    if event.kind == "fit_failed":
        why = event.message.removeprefix("fit failed: ").split(" (")[0].split(":")[0]
        why = re.sub(r"\d+(\.\d+)?%", "too little", why)
    elif event.kind == "rejected":
        why = f"candidate rejected ({event.data.get('reason')})"
    else:
        return
    refusals[why] = refusals.get(why, 0) + 1


def _why_none(calibrator, refusals: dict, m) -> str:
    """Why the replay ended without a calibration, in plain words: what refused the fits, the
    coverage each environment reached, and whether the samples ``m`` (N,3) lie on one sphere."""
    parts = []
    if refusals:
        top = sorted(refusals.items(), key=lambda kv: -kv[1])[:3]
        parts.append("fits refused: " + "; ".join(f"{n}× {why}" for why, n in top))
    else:
        parts.append("no fit was tried: the stored samples never covered "
                     f"{100 * calibrator.policy.min_coverage:.0f}% of the sphere")
    envs = calibrator.environment_summary()
    cover = ", ".join(
        f"t={e['start']:.1f}–" + (f"{e['end']:.1f}" if e["end"] is not None else "end")
        + f" s: {percent(e['coverage'])}" for e in envs if e["start"] is not None)
    if len(envs) > 1:
        parts.append(f"the field changed {len(envs) - 1} time(s); coverage per environment: "
                     f"{cover}, each short of the {100 * calibrator.policy.min_coverage:.0f}% "
                     "a first fit needs")
    else:
        parts.append(f"the stored samples' coverage of the sphere: "
                     f"{percent(envs[-1]['coverage'])} "
                     f"({100 * calibrator.policy.min_coverage:.0f}% needed)"
                     if envs[-1]["coverage"] is None else
                     f"the stored samples cover {100 * envs[-1]['coverage']:.0f}% of the "
                     f"sphere ({100 * calibrator.policy.min_coverage:.0f}% needed)")
    from ..fitting.sphere_stream import sphere_spread

    spread = sphere_spread(m)
    if spread is not None and spread > _ONE_SPHERE:
        parts.append(f"the samples lie on no one sphere (spread {100 * spread:.0f}% of the "
                     "field): the field probably changed during the recording (a magnet "
                     "attached or removed, the board moved near iron) while the board turned "
                     "too little to tell the environments apart, and no one environment has "
                     "the coverage a calibration needs")
    return "; ".join(parts)
