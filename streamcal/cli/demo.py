"""``streamcal demo``: the out-of-the-box main job (docs/cli.md), no hardware and no network needed.

1. Replays the bundled recorded track (``streamcal/data/demo_track.csv.gz``, or ``--track``)
   through the real MPU-9250 I²C driver on the register-level fake bus into the streaming
   calibrator (fits run synchronously, so the output is the same on every run), printing each
   accepted calibration as coverage grows and a map of the sphere at coverage milestones.
2. Diagnoses the samples the driver produced: verdict, ranked candidate effects, and the model
   ladder falling to the noise floor once the missing effect is added.
3. Writes the HTML report and the track the driver produced (``streamcal-demo-report.html``,
   ``streamcal-demo-track.csv.gz``) into ``--out-dir``, or a new temporary directory when
   neither ``--out-dir`` nor ``-o`` is given (so a demo run leaves nothing in the current
   directory), and says where; the suggested ``streamcal fit … --add`` names that track by its
   absolute path, so it works when pasted.
"""
from __future__ import annotations

import contextlib
import functools
import html
import importlib.resources
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from ..calibration import DEFAULT_MODEL
from ..stream.coverage import coverage_words, percent
from ..atomic import is_stdout, output_dir, prepare_output
from ._output import messages_to
from .diagnose import candidate_table, residual_name

DEFAULT_REPORT = "streamcal-demo-report.html"
#: The driver's samples as a track, written beside the report.
TRACK_NAME = "streamcal-demo-track.csv.gz"
#: Coverage fractions at which the map of the sphere is printed (first crossing of each).
MAP_AT = (0.35, 0.65)
BLOCK_SIZE = 50
BAR_WIDTH = 30


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="replay the bundled track through the fake-bus driver "
                              "and the streaming calibrator, diagnose it, write a report",
                              description="The out-of-the-box main job, no hardware and no "
                                          "network needed: replay the bundled track through the "
                                          "fake-bus MPU-9250 driver and the streaming "
                                          "calibrator, diagnose it, write a report.")
    p.add_argument("--track", metavar="PATH", help="demo another track instead of the bundled one")
    p.add_argument("-o", "--output", metavar="HTML",
                   help=f"report file (default: {DEFAULT_REPORT}; relative to --out-dir when "
                        "given, else to the current directory; - for stdout, the messages then "
                        "go to stderr)")
    p.add_argument("--out-dir", metavar="DIR", help="directory for the report and the track "
                   "(created; default: a new temporary directory unless -o is given)")
    p.add_argument("--quiet", action="store_true",
                   help="print only the verdict, the top candidate and the report's path")
    p.set_defaults(func=run)


@contextlib.contextmanager
def bundled_track():
    """Path of the bundled demo track (a real file even from a zipped install)."""
    ref = importlib.resources.files("streamcal").joinpath("data/demo_track.csv.gz")
    with importlib.resources.as_file(ref) as path:
        yield Path(path)


def report_path(output: str | None, out_dir: str | None) -> Path:
    """Where the report goes: ``output`` (relative to ``out_dir`` when given, else to the
    current directory); with neither, ``DEFAULT_REPORT`` in a new temporary directory.
    ``-`` (stdout) stays ``-``."""
    if output is None and out_dir is None:
        out_dir = tempfile.mkdtemp(prefix="streamcal-demo-")
    path = Path(output or DEFAULT_REPORT)
    if out_dir and not path.is_absolute() and not is_stdout(path):
        path = Path(out_dir) / path
    return path


def track_dir(out: Path, out_dir: str | None) -> Path:
    """Where the driver's track goes: beside the report, or in ``out_dir`` (a new temporary
    directory when neither is a place) when the report goes to stdout."""
    if not is_stdout(out):
        return out.parent
    return Path(out_dir or tempfile.mkdtemp(prefix="streamcal-demo-"))


def run(args) -> int:
    with contextlib.ExitStack() as stack:
        track_path = Path(args.track) if args.track else stack.enter_context(bundled_track())
        source = _open(track_path)   # a track the driver cannot replay: said before any output
        out = report_path(args.output, args.out_dir)
        directory = track_dir(out, args.out_dir)
        prepare_output(out)             # a place that cannot be written is said before the work
        output_dir(directory)
        return _demo(track_path, source, out, directory, args.quiet)


def _open(track_path: Path):
    """The fake-bus MPU-9250 source replaying ``track_path`` (the driver brought up)."""
    from firmware_bridge.i2c_source import open_i2c_source

    from ..inputs.track import Track

    return open_i2c_source(f"fake:{track_path}", block_size=BLOCK_SIZE, read_track=Track.read)


def _demo(track_path: Path, source, out: Path, directory: Path, quiet: bool) -> int:
    from ..report import diagnose_or_reason, write_report
    from ..inputs.track import Track

    tell = functools.partial(print, file=messages_to(out))
    say = (lambda *a, **k: None) if quiet else tell
    start = time.monotonic()
    say(f"streamcal demo: replaying {track_path.name} through the MPU-9250 driver on a "
        f"simulated I²C bus (fake:{track_path})")
    blocks, accepted, calibrator = _replay(source, say)
    if not blocks:
        from ..errors import InsufficientDataError
        raise InsufficientDataError(f"{track_path}: the driver produced no samples")
    say(f"\n{calibrator.n_ingested} magnetometer samples from the driver, {calibrator.n_fits} "
        f"fits, {len(accepted)} accepted; final {coverage_words(calibrator.buffer.measured_fraction)}")
    from ..report import coverage_view
    say(coverage_view(calibrator.buffer))

    track = Track.from_blocks(blocks, metadata={"source": f"fake:{track_path.name} via the "
                                                "MPU-9250 driver", "description": "streamcal demo"})
    say(f"\ndiagnosing the {len(track.t_mag)} recorded samples "
        f"(model {', '.join(DEFAULT_MODEL)}; every candidate effect is refitted)…")
    recorded = (directory / TRACK_NAME).resolve()
    diagnosis, reason = diagnose_or_reason(track, DEFAULT_MODEL, recording=[str(recorded)])
    if diagnosis is None:
        tell(f"no diagnosis: {reason}")
    else:
        tell(_verdict(diagnosis))
        say(_candidates(diagnosis))
        say(_ladder(diagnosis))
    track.write(recorded)
    if diagnosis is not None and diagnosis.next_step:
        import shlex

        tell(f"\nnext step (gives the rms promised above): "
             f"{' '.join(shlex.quote(w) for w in diagnosis.next_step)}")
    path = write_report(out, track, diagnosis, reason=reason, name=track_path.name,
                        title=f"streamcal demo: {track_path.name}",
                        intro=_stream_html(accepted, track.mag_unit))
    tell(f"\nreport written to {path if is_stdout(path) else path.resolve()}")
    tell(f"track the driver produced: {recorded}")
    say(f"(done in {time.monotonic() - start:.0f} s)")
    return 0 if diagnosis is not None else 1


def _replay(source, say):
    from ..report import coverage_view
    from ..stream import CoverageBuffer, StreamingCalibrator

    calibrator = None
    blocks, accepted, maps_done = [], [], set()
    for block in source:
        blocks.append(block)
        if calibrator is None:
            covariates = (("temp",) if block.temp is not None else ()) + tuple(block.aux)
            calibrator = StreamingCalibrator(model=DEFAULT_MODEL, synchronous=True,
                                             buffer=CoverageBuffer(covariates=covariates))
        for event in calibrator.ingest(block):
            _event(event, calibrator, accepted, maps_done, say, coverage_view)
    if calibrator is not None:
        for event in calibrator.close():
            _event(event, calibrator, accepted, maps_done, say, coverage_view)
    return blocks, accepted, calibrator


def _event(event, calibrator, accepted, maps_done, say, coverage_view) -> None:
    when = f"[{event.t:7.1f} s]" if event.t is not None and math.isfinite(event.t) else " " * 11
    if event.kind == "accepted":
        cal = calibrator.calibration
        field = cal.field or cal.radius
        coverage = event.data.get("coverage_at_fit", cal.coverage)
        accepted.append({"t": event.t, "coverage": coverage, "rms": cal.rms, "field": field,
                         "b": np.asarray(cal.b).tolist()})
        say(f"{when} calibration #{len(accepted)} accepted: coverage {percent(coverage, 3)}, "
            f"rms {cal.rms:.3f} {_unit(cal.unit)}, field {field:.2f} {_unit(cal.unit)}")
    elif event.kind == "coverage":
        frac = calibrator.buffer.fraction
        due = [m for m in MAP_AT if frac >= m and m not in maps_done]
        if due:
            maps_done.update(due)
            say(f"{when} " + coverage_view(calibrator.buffer).replace("\n", "\n" + " " * 12))
        else:
            say(f"{when} {event.message.split(':')[0]}")
    elif event.kind in ("rejected", "fit_failed", "drift", "forgot", "disturbance"):
        say(f"{when} {event.message}")


def _unit(unit: str) -> str:
    from ..units import display_unit

    return display_unit(unit)


def _verdict(d) -> str:
    """The diagnosis' plain sentences, then the verdict with its numbers."""
    import textwrap

    u = _unit(d.calibration.unit if d.calibration is not None else "uT")
    cmd = " ".join(d.next_step) if d.next_step else ""
    text = d.summary.replace(f" To do: {cmd}", "") if cmd else d.summary
    floor = (f"noise floor {d.noise_floor:.3f} {u} ({d.rms / d.noise_floor:.2f}× the floor)"
             if d.floor_known else f"noise floor not measurable ({d.noise_floor_reason})")
    return ("\n" + "\n".join(textwrap.wrap(text, 96)) + f"\n\nverdict: {d.verdict} — rms "
            f"{d.rms:.3f} {u} on the {residual_name(d.residual)} residual with "
            f"{', '.join(d.model)} over {d.ladder[0]['n']} samples, {floor}; "
            f"{d.n_outliers} of {d.n} samples are outliers of that model\n  (rule: "
            f"{d.significance_rule if d.verdict == 'effect_missing' else d.noise_floor_rule})")


def _candidates(d) -> str:
    if not d.candidates:
        return "\nno candidate effect can be tried on this track"
    return "\n".join([""] + candidate_table(d, numbered=True))


def _ladder(d) -> str:
    steps = d.ladder or [{"model": list(d.model), "rms": d.rms}]
    known = d.floor_known
    top = max([s["rms"] for s in steps] + ([d.noise_floor] if known else []))
    lines = ["", "model ladder: rms after adding each effect"]

    def row(name, value, ratio):
        bar = "█" * max(1, int(round(BAR_WIDTH * value / top)))
        return f"  {name:<30}{value:>8.3f}{ratio:>14}  {bar}"

    for step in steps:
        name = "+ " + step["added"] if "added" in step else ", ".join(step["model"])
        residual = step.get("residual", "sensor")
        # the floor is the sensor residual's: a tied step says which residual it is on instead
        ratio = f"{step['rms'] / d.noise_floor:.2f}× floor" if residual == "sensor" and known \
            else residual_name(residual)
        lines.append(row(name, step["rms"], ratio))
    if known:
        lines.append(row("noise floor", d.noise_floor, ""))
    return "\n".join(lines)


def _stream_html(accepted, unit: str) -> str:
    u = _unit(unit)
    if not accepted:
        return "<p>The streaming calibrator accepted no calibration during the replay.</p>"
    rows = "".join(f"<tr><td class=\"num\">{a['t']:.1f}</td><td class=\"num\">"
                   f"{percent(a['coverage'])}</td><td class=\"num\">{a['rms']:.3f}</td>"
                   f"<td class=\"num\">{a['field']:.2f}</td></tr>" for a in accepted)
    return ("<h2>Streaming: calibrations accepted as coverage grew</h2><p>The track was replayed "
            "through the MPU-9250 driver on a simulated I²C bus into the streaming calibrator.</p>"
            f"<table><thead><tr><th>t (s)</th><th>coverage</th><th>rms ({html.escape(u)})</th>"
            f"<th>field ({html.escape(u)})</th></tr></thead><tbody>{rows}</tbody></table>")
