"""``streamcal diagnose TRACK [--model a,b] [--json] [--plots DIR]`` (SPEC §4)."""
from __future__ import annotations

import argparse
import importlib
import json
import sys

from ..errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser("diagnose", help="compare the model with the measurements and name "
                              "the missing effect")
    p.add_argument("track", help="track file (.csv or .csv.gz, SPEC §1)")
    p.add_argument("--model", default="hard_iron,soft_iron",
                   help="comma-separated effects of SPEC §3 (default: hard_iron,soft_iron)")
    p.add_argument("--json", action="store_true", help="print one JSON object (SPEC §4)")
    p.add_argument("--plots", metavar="DIR", help="write figures of the residuals into DIR")
    p.set_defaults(func=run)


def _report_module():
    try:
        return importlib.import_module("streamcal.report")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("streamcal.report"):
            raise InputError("--plots needs streamcal.report, which this installation lacks") from None
        raise


def run(args: argparse.Namespace) -> int:
    from ..diagnose import diagnose
    from ..track import Track

    model = tuple(n.strip() for n in args.model.split(",") if n.strip())
    report = _report_module() if args.plots else None
    track = Track.read(args.track)
    result = diagnose(track, model=model)
    if report is not None:
        report.write_diagnosis_plots(result, track, args.plots)
    if args.json:
        print(json.dumps(result.to_dict(), allow_nan=False, default=lambda v: None))
        return 0
    print(_text(result))
    return 0


def _text(d) -> str:
    lines = [f"model      {', '.join(d.model)}",
             f"samples    {d.n} ({d.n_outliers} outliers)",
             f"rms        {d.rms:.4g}   noise floor {d.noise_floor:.4g}",
             f"verdict    {d.verdict}"]
    if d.candidates:
        lines += ["", f"{'candidate':<24}{'rms after':>10}{'p-value':>11}  evidence"]
        lines += [f"{c.effect:<24}{c.rms_after:>10.4g}{c.p_value:>11.2e}  {c.evidence}"
                  for c in d.candidates]
    if d.ladder:
        lines += ["", "model ladder", f"{'step':<34}{'rms':>10}{'× floor':>9}"]
        for step in d.ladder:
            name = "+ " + step["added"] if "added" in step else ", ".join(step["model"])
            if step.get("gravity_tied"):
                name += " (gravity-tied)"  # rms of the gravity-tied residual, another scale
            elif step.get("gyro_tied"):
                name += " (gyro-tied)"     # rms of the gyro-tied residual, another scale
            ratio = step["rms"] / d.noise_floor if d.noise_floor else float("nan")
            lines.append(f"{name:<34}{step['rms']:>10.4g}{ratio:>9.2f}")
        lines.append(f"{'noise floor':<34}{d.noise_floor:>10.4g}{1.0:>9.2f}")
    if d.outlier_spans:
        lines += ["", "outlier spans (s): " + ", ".join(f"[{a:.2f}, {b:.2f}]" for a, b in d.outlier_spans)]
    return "\n".join(lines)
