"""``streamcal diagnose TRACK [--model a,b] [--json] [--plots DIR]`` (docs/cli.md)."""
from __future__ import annotations

import argparse
import functools
import importlib
import json
import math
import sys

from ..calibration import jsonable
from ..errors import InputError, InsufficientDataError
from ._common import (RECORDING_HELP, add_input_options, recording_argv, recording_chunks,
                      verdict_line)
from ._location import (add_location_options, attitude_lines, beside_diagnosis,
                        location_reference)


def register(subparsers) -> None:
    p = subparsers.add_parser("diagnose", help="compare the model with the measurements and name "
                              "the missing effect",
                              description="Fit the model to a recording, compare it with the "
                                          "measurements and the noise floor, say where it fails "
                                          "and which catalog effect is missing (verdict "
                                          "at_noise_floor, effect_missing or unexplained; see "
                                          "docs/diagnosis.md).")
    p.add_argument("track", help=RECORDING_HELP)
    add_input_options(p, skip_bad_rows=True)
    p.add_argument("--model", default="hard_iron,soft_iron",
                   help="comma-separated effects (docs/effects.md; default: hard_iron,soft_iron)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (keys in docs/diagnosis.md)")
    p.add_argument("--plots", metavar="DIR", help="write figures of the residuals into DIR")
    p.add_argument("--cal", metavar="CAL", help="diagnose against this calibration (JSON file or "
                   "daemon/replay state dir; its model replaces --model; 'autopilot' or 'log': "
                   "the one in the log's own parameters, ArduPilot COMPASS_* or PX4 "
                   "CAL_MAGn_*): re-estimate only what the track determines, hold the rest")
    add_location_options(p)
    p.add_argument("--full", action="store_true", help="diagnose every sample even of a long "
                   "recording (default: recordings of more than 60 000 magnetometer samples, "
                   "in any format, are diagnosed from a stratified subsample; the output says "
                   "which samples were used)")
    p.set_defaults(func=run)


def _report_module():
    try:
        return importlib.import_module("streamcal.report")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("streamcal.report"):
            raise InputError("--plots needs streamcal.report, which this installation lacks") from None
        raise


def run(args: argparse.Namespace) -> int:
    from ..diagnosis.subsample import LONG_SAMPLES, diagnose_recording

    model = tuple(n.strip() for n in args.model.split(",") if n.strip())
    from ._calarg import follow_fitted_compass

    follow_fitted_compass(args)
    if getattr(args, "compass", None) == "all":
        from ._compasses import diagnose_all
        return diagnose_all(args, model, describe=lambda d: _text(d) + held_text(d))
    from ..geomag import text_lines

    report = _report_module() if args.plots else None
    ref = location_reference(args)
    calibration_of = None
    if getattr(args, "cal", None):
        from ._calarg import calibration_for

        calibration_of = functools.partial(calibration_for, args.cal)
    try:
        result, track = diagnose_recording(
            recording_chunks(args, rows=100_000), model,
            long_samples=float("inf") if args.full else LONG_SAMPLES,
            calibration_of=calibration_of, recording=recording_argv(args),
            cal_arg=getattr(args, "cal", None), location=ref)
    except InsufficientDataError as exc:
        return _refused(args, exc, ref)
    plots = ""
    if report is not None:
        written = report.write_diagnosis_plots(result, track, args.plots)
        plots = plots_written(args.plots, written)
    # at the given place, else the log's GPS: what the library used
    attitude = beside_diagnosis(track, result)
    local = attitude.pop("reference_field")
    if args.json:
        out = result.to_dict()
        out["reference_field"] = local
        out.update(attitude)
        print(json.dumps(jsonable(out), allow_nan=False))
        if plots:   # stdout stays one JSON object
            print(plots, file=sys.stderr)
        return 0
    print(_headline(result) + "\n\n" + _text(result) + held_text(result) + "\n\n"
          + "\n".join(text_lines(local) + attitude_lines(attitude)))
    if plots:
        print(plots)
    return 0


def _refused(args, exc, ref) -> int:
    """No diagnosis (the data cannot support one): what the logged attitude and the World
    Magnetic Model still say about the calibration in force (a PX4 log that carries only the
    calibrated field, a vehicle that did not turn), then the refusal; exit 1."""
    from ..fitting.attitude_reference import log_attitude_reference

    track = getattr(exc, "track", None)
    attitude = log_attitude_reference(track, ref, None) if track is not None else {}
    if not (attitude.get("attitude_reference") or {}).get("n"):
        raise exc
    if args.json:
        print(json.dumps(jsonable({"verdict": None, "refused": str(exc), **attitude}),
                         allow_nan=False))
    else:
        print("\n".join([f"no diagnosis: {exc}"] + attitude_lines(attitude)))
    return 1


def _headline(d) -> str:
    """The plain sentences first, wrapped, then the command they advise on a line of its own."""
    import textwrap

    text = d.summary or ""
    cmd = " ".join(d.next_step) if d.next_step else ""
    if cmd:
        text = text.replace(f" To do: {cmd}", "")
    lines = textwrap.wrap(text, 96)
    if cmd:
        lines += ["", "next step: " + cmd]
    return "\n".join(lines)


def plots_written(directory, paths) -> str:
    """``plots: 7 PNG files written to /abs/dir``."""
    from pathlib import Path

    n = len(paths)
    return (f"plots: {n} PNG file{'s' if n != 1 else ''} written to "
            f"{Path(directory).resolve()}")


def held_text(d) -> str:
    """The lines of a diagnosis against held parameters (empty for a fresh fit)."""
    h = d.held
    if h is None:
        return ""
    from ..units import display_unit

    unit = display_unit(d.unit) or "sensor unit"
    lines = ["", f"against    {h.calibration_source}",
             f"held       {', '.join(h.parameters) or 'none'} (predicted error above "
             f"{h.tolerance:.3g} {unit} at the given or the fitted point, or not in the "
             "model)"]
    n_r = h.n_ranked or d.n
    if n_r < d.n:
        lines.append(f"ranked     candidates refitted on {n_r} of {d.n} samples (every cell of "
                     "direction × stretch of time kept); the effects the ladder adds were refitted "
                     "on every sample, the others' numbers are on those")
    scores = list(h.aux_channels.items())[:4]
    if scores:
        lines.append("channels   residual follows, each alone: "
                     + ", ".join(f"{k} r={v:.2f}" for k, v in scores))
    if h.estimated:
        lines.append("re-estimated (value ± σ from this recording, " + unit + ")")
        lines += [f"  {k:<8}{v['value']:>12.5g} ± {v['sigma']:.3g}" for k, v in h.estimated.items()]
    lines += _recheck_lines(d, unit)
    lines += _gyro_lines(d, unit)
    used = h.attitude_reference
    if used:
        lines += [f"attitude   the held fit also fitted the field's direction against the attitude "
                  f"reference ({used['samples']} samples, width {used['width_deg']:.2g}°)",
                  f"           caveat: {used['caveat']}"]
    return "\n".join(lines)


def _gyro_lines(d, unit: str) -> list[str]:
    """Held parameters the gyro link pinned (:mod:`streamcal.diagnosis.held.gyro_pin`), or why not."""
    link = d.held.gyro_link
    if not link:
        return []
    pinned = d.held.gyro_pinned
    if not pinned:
        return [f"gyro link  not used: {link.get('reason', '')}"]
    lines = ["pinned by the gyro link (value ± σ, " + unit + "; " + link.get("rule", "") + ")"]
    lines += [f"  {k:<8}{v['value']:>12.5g} ± {v['sigma']:.3g} (held value {v['held_value']:.5g})"
              for k, v in pinned.items()]
    checks = (link.get("guard") or {}).get("held_check", {})
    lines += [f"  the gyro link says {k} held at {c['held_value']:.5g} is off by "
              f"{c['difference']:+.3g} ± {c['link_sigma']:.2g} ({c['z']:+.1f} σ; the pinned "
              f"values do not depend on it)" for k, c in checks.items()
              if c.get("z") is not None and abs(c["z"]) >= 3]
    return lines


def _held_value(d, name: str, entry) -> str:
    """The value a held core parameter keeps (the report's "held" value), as text."""
    try:
        return f"{entry(d.calibration.K, d.calibration.b, name):.5g}"
    except (KeyError, ValueError, IndexError):
        return "the given value"


def _recheck_lines(d, unit: str) -> list[str]:
    """The re-check at the fitted point (:mod:`streamcal.diagnosis.held.recheck`) and how the
    held fit ended."""
    lines = []
    status = d.held.fit_status
    if status:
        lines.append(f"held fit   {status['status']} after {status['iterations']} iterations"
                     + (f" ({status['message']})" if status.get("message") else ""))
    after = d.held.held_after_fit
    if after:
        lines.append("held after the fit (rule: at the fitted point σ ≤ the tolerance and the "
                     "value within its plausible range ± 3 σ, else the worst is held and the "
                     "fit repeated)")
        from ..fitting.entries import entry

        lines += [f"  {h['parameter']:<8} held at {_held_value(d, h['parameter'], entry)} {unit} "
                  f"(the fit had moved it to {h['value']:.5g} ± {h['sigma']:.3g}): "
                  f"{h['reason']}" for h in after]
    for k, v in d.held.suspicious.items():
        lines.append(f"SUSPICIOUS {k} {v['value']:.5g} ± {v['sigma']:.3g} {unit}: {v['reason']} "
                     "(kept: it is what the recording is asked for)")
    return lines




def _change(before: float, after: float, digits: int = 4) -> str:
    """``after / before − 1`` in percent ("-39%", "±0%"), of the two numbers as shown
    (``digits`` significant digits)."""
    from ..diagnosis.story import change_percent

    pct = change_percent(before, after, digits)
    if pct is None:
        return ""
    pct = round(pct)
    return f"{pct:+d}%" if pct else "±0%"


def residual_name(residual: str) -> str:
    """How a residual family is called in text ("gravity-tied")."""
    from ..diagnosis.diagnosis import RESIDUAL_LABELS

    return RESIDUAL_LABELS.get(residual, residual)


def candidate_table(d, numbered: bool = False) -> list[str]:
    """The ranked candidates of a :class:`~streamcal.diagnose.Diagnosis`, one line each (with a
    rank column if ``numbered``), every ``rms_after`` beside the rms of the model without it on
    the same residual, with the significance and materiality tests apart and the rule that
    decides them printed below."""
    def rank(k):
        return f"{k:<5}" if numbered else ""
    u = _diagnosis_unit(d)
    lines = [f"{rank('rank')}{'candidate':<24}{'residual':>13}{'before':>9}{'after':>9}{'change':>8}"
             f"{'n':>8}{'p-value':>11}{'signif.':>8}{'material':>9}  evidence (rms in {u} over "
             "the n samples the model with the effect keeps)"]
    for k, c in enumerate(d.candidates, 1):
        row = d.candidate_dict(c)
        before = row["rms_before"]
        lines.append(f"{rank(k)}{c.effect:<24}{residual_name(row['residual']):>13}{before:>9.4g}"
                     f"{c.rms_after:>9.4g}{_change(before, c.rms_after):>8}{row['n']:>8}"
                     f"{c.p_value:>11.2e}{'yes' if row['significant'] else 'no':>8}"
                     f"{'yes' if row['material'] else 'no':>9}  {c.evidence}")
    if d.verdict != "effect_missing":
        lines.append(f"(rule: {d.significance_rule}; an effect is missing only when both hold)")
    if any(d.baseline(c)[0] != "sensor" for c in d.candidates):
        lines.append("(each candidate against the model without it on the same residual; "
                     "the tied residuals include the gravity reference's or the gyro's error "
                     "and are not comparable with the sensor rms)")
    return lines


def _diagnosis_unit(d) -> str:
    from ..diagnosis.text import diagnosis_unit
    from ..units import display_unit

    return display_unit(diagnosis_unit(d))


def _text(d) -> str:
    """Every rms beside the rms it is compared with on the same residual, each named (see
    :class:`streamcal.diagnose.Diagnosis`); "× floor" against the floor of the residual each
    rms is on (a tied residual's own), where the recording measured it."""
    from ..diagnosis.misfit import summary

    known = d.floor_known
    u = _diagnosis_unit(d)
    floor = f"noise floor {d.noise_floor:.4g} {u}" if known else "noise floor not measurable"
    last = d.ladder[-1] if d.ladder else {"n_outliers": d.n_outliers}
    outliers = (f"{d.n_outliers} outliers" if len(d.ladder) < 2 else
                f"outliers: {last['n_outliers']} of the last model of the ladder, {d.n_outliers} "
                f"of the model as given, whose missing effects push samples out")
    lines = [f"model      {', '.join(d.model)}",
             f"samples    {d.n} ({outliers})",
             f"rms        {d.rms:.4g} {u} ({residual_name(d.residual)} residual, over the "
             f"{d.ladder[0]['n'] if d.ladder else d.n - d.n_outliers} samples of the ladder)   "
             f"{floor}"]
    if getattr(d, "sampling", None):
        s = d.sampling
        lines.insert(2, f"used       {s['samples_used']} of {s['samples_total']} magnetometer "
                        f"samples ({s['subsample_rule']}); outlier spans over the "
                        f"{s['outlier_spans_over']}")
    if not known:
        lines.append(f"           why: {d.noise_floor_reason}")
    for residual, entry in (d.tied_noise_floors or {}).items():
        name = residual_name(residual)
        if entry.get("reliable"):
            lines.append(f"           {name} floor {entry['floor']:.4g} {u} (magnetometer noise "
                         f"{entry['magnetometer_part']:.3g}, reference "
                         f"{entry['reference_part']:.3g} {u})")
        else:
            lines.append(f"           {name} floor not measurable: {entry.get('reason', '')}")
    lines.append(verdict_line(d))
    if d.verdict == "unexplained" and d.misfit:
        lines += ["", "where the misfit sits (share of the residual energy vs share of samples)"]
        lines += ["  " + line for line in summary(d.misfit)]
    if d.candidates:
        lines += [""] + candidate_table(d)
    if d.ladder:
        ratio_head = f"{'× floor':>9}" if known else ""
        n = d.ladder[0].get("n")
        lines += ["", f"model ladder (rms in {u} over the same {n} samples: those the last model "
                      "keeps; outliers: each model's own)",
                  f"{'step':<34}{'residual':>13}{'before':>9}{'rms':>9}" + ratio_head
                  + f"{'outliers':>10}"]
        for step in d.ladder:
            name = "+ " + step["added"] if "added" in step else ", ".join(step["model"])
            residual = step.get("residual", "sensor")
            before = f"{step['rms_before']:>9.4g}" if "rms_before" in step else " " * 9
            ratio = ""
            if known:   # × the floor of the residual the rms is on
                floor = d.floor_for(residual)
                ratio = f"{step['rms'] / floor:>9.2f}" if math.isfinite(floor) and floor > 0 \
                    else f"{'–':>9}"
            lines.append(f"{name:<34}{residual_name(residual):>13}{before}"
                         f"{step['rms']:>9.4g}{ratio}{step.get('n_outliers', ''):>10}")
        if known:
            lines.append(f"{'noise floor':<34}{'sensor':>13}{'':>9}{d.noise_floor:>9.4g}"
                         f"{1.0:>9.2f}")
            for residual in d.tied_noise_floors or {}:
                floor = d.floor_for(residual)
                if math.isfinite(floor):
                    lines.append(f"{'noise floor':<34}{residual_name(residual):>13}{'':>9}"
                                 f"{floor:>9.4g}{1.0:>9.2f}")
    if d.outlier_spans:
        lines += ["", "outlier spans (s): " + ", ".join(f"[{a:.2f}, {b:.2f}]" for a, b in d.outlier_spans)]
    return "\n".join(lines)
