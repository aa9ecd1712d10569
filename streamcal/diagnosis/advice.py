"""What a diagnosis tells its user first: the plain sentences (``summary``), the command that
does what they advise (``next_step``, an argv list) and the heading error its residual implies
(``heading_error_deg``).

Every number here is one the ladder shows (:mod:`streamcal.diagnosis.story`): the rms before is
``ladder[0]``, the rms promised is the last step's, both over the ladder's ``n`` samples, and the
percentage is computed from those two numbers.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..units import display_unit
from .story import change_percent

#: A phrase that says what a tied residual is, the first time the summary names it.
RESIDUAL_GLOSS = {"gravity_tied": "gravity-tied residual (each reading's direction tied to the "
                                  "accelerometer's gravity)",
                  "gyro_tied": "gyro-tied residual (each reading's direction carried by the "
                               "gyro)"}
#: How the heading error is estimated from an rms field error (``heading_error_deg["rule"]``).
HEADING_RULE = ("atan(rms / H): the angle a field error of the rms turns the horizontal "
                "field H when it lies across it; an error in the field's direction, which the "
                "field's size cannot show, comes on top (heading_check: against the attitude)")


def next_step(d, recording: Sequence[str], cal_arg: str | None = None,
              output: str = "refined.json", place: Sequence[str] = ()) -> list[str] | None:
    """The argv that fits the ladder's last model on this recording (None when the ladder adds
    nothing): ``fit REC --add E …`` for a fresh diagnosis, ``fit REC --cal CAL --add E … -o
    OUTPUT`` for one against a held calibration, with ``place`` (:func:`place_argv`) after the
    effects."""
    added = [s["added"] for s in d.ladder[1:]]
    if not added:
        return None
    argv = ["streamcal", "fit", *recording]
    if d.held is not None:
        default = str(d.held.calibration_source).startswith("default")
        argv += ["--cal", "default" if default else (cal_arg or "CAL.json")]
    elif tuple(d.model) != ("hard_iron", "soft_iron"):
        argv += ["--model", ",".join(d.model)]
    for name in added:
        argv += ["--add", name]
    argv += list(place)
    if d.held is not None:
        argv += ["-o", output]
    return argv


def place_argv(location: dict) -> list[str]:
    """``--lat … --lon … --alt-km … --date …`` of a :func:`streamcal.geomag.wmm_field` result,
    the numbers as Python writes them (read back exactly)."""
    return ["--lat", repr(float(location["lat"])), "--lon", repr(float(location["lon"])),
            "--alt-km", repr(float(location["alt_km"])), "--date", str(location["date"])]


def horizontal_field(track, calibration, location: dict | None,
                     gravity=None) -> tuple[float | None, str]:
    """``(H, where)``: the horizontal field (µT) from the World Magnetic Model at ``location``
    (:func:`streamcal.geomag.wmm_field`), else from the recording (fitted field × cos dip, dip
    from the accelerometer, ``gravity`` its reference when given); ``(None, why not)``
    otherwise."""
    if location is not None:
        h = location["intensity_uT"] * math.cos(math.radians(location["inclination_deg"]))
        return h, "World Magnetic Model at the given place"
    unit = getattr(calibration, "unit", None) or track.mag_unit
    if unit != "uT":
        return None, f"the readings are in {display_unit(unit) or 'an unknown unit'}, not µT"
    if not track.has("accel"):
        return None, ("the horizontal field is unknown: the recording has no accelerometer "
                      "and no place was given (--lat/--lon)")
    from .reference_field import fitted_dip

    dip, _ = fitted_dip(track, calibration, gravity)
    strength = calibration.field or calibration.radius
    if dip is None or not strength:
        return None, "the fitted dip could not be measured"
    return strength * math.cos(math.radians(dip)), "fitted field and dip of this recording"


def heading_error(d, h: float | None) -> dict | None:
    """``{"before", "after", "H_uT", "rule"}`` (degrees) for the ladder's first and last rms on
    the sensor residual; None when ``h`` is unknown or the ladder is on another residual."""
    steps = [s for s in d.ladder if s.get("residual", "sensor") == "sensor"]
    if h is None or not h > 0 or not steps:
        return None

    def deg(rms):
        return float(math.degrees(math.atan2(rms, h))) if np.isfinite(rms) else None
    return {"before": deg(steps[0]["rms"]), "after": deg(steps[-1]["rms"]), "H_uT": float(h),
            "rule": HEADING_RULE}


def heading_sentences(d) -> list[str]:
    """What the logged attitude says of the refinement ``next_step`` writes (``heading_check``):
    its heading error beside the held calibration's, and a warning when it points worse."""
    check = d.heading_check or {}
    if check.get("rms_after") is None:
        return []
    before, after = check["rms_before"], check["rms_after"]
    held = getattr(d, "held", None)
    joint = (" The refinement fits the field's direction against that attitude too; its yaw "
             "is itself steered by the compass." if held is not None and held.attitude_reference
             else "")
    if not check.get("worse"):
        return [f"Against the logged attitude the heading error goes from {before:.2f}° to "
                f"{after:.2f}° rms.{joint}"]
    recording = list(d.next_step[2:d.next_step.index("--cal")]) if d.next_step and \
        "--cal" in d.next_step else ["FLIGHT"]
    return [f"Careful: against the logged attitude that refinement points the compass worse "
            f"(heading error {before:.2f}° → {after:.2f}° rms): this recording fixes the "
            f"field's size, not its direction; `streamcal fit {' '.join(recording)} "
            f"--attitude` fits against the attitude instead."]


def summary(d) -> str:
    """Two to four plain sentences: what is wrong, how large, what to do."""
    u = display_unit(getattr(d.calibration, "unit", None) or getattr(d, "unit", "") or "uT") \
        or "sensor units"
    first, last = d.ladder[0], d.ladder[-1]
    heading = d.heading_error_deg or {}
    size = f"{first['rms']:.3g} {u}"
    if heading.get("before") is not None:
        size += f" (worth up to {heading['before']:.1f}° of heading)"
    if len(d.ladder) > 1:
        added = [s["added"] for s in d.ladder[1:]]
        what = added[0] if len(added) == 1 else ", ".join(added[:-1]) + " and " + added[-1]
        text = [f"The model {', '.join(d.model)} misses {what}: the field error is {size}."]
        if last["residual"] == first["residual"]:
            start, where = first["rms"], ""
        else:   # compared on the tied residual, from the model without it on that residual
            start = next(s["rms_before"] for s in d.ladder[1:]
                         if s["residual"] == last["residual"])
            where = f" on the {RESIDUAL_GLOSS.get(last['residual'], last['residual'])}"
        pct = change_percent(start, last["rms"], 3)
        after = f"{last['rms']:.3g} {u}"
        if heading.get("after") is not None and not where:
            after += f", {heading['after']:.1f}°"
        change = "" if pct is None else f"{pct:+.0f}%, "
        text.append(f"With {what} added the rms{where} falls from {start:.3g} to {after} "
                    f"({change}over the same {first['n']} samples).")
        text += heading_sentences(d)
        cmd = " ".join(d.next_step) if d.next_step else ""
        if cmd:
            text.append(f"To do: {cmd}")
        return " ".join(text)
    if d.verdict == "at_noise_floor":
        noise = {"gravity_tied": "the sensor's noise and the error of the accelerometer's "
                                 "gravity direction it is compared with",
                 "gyro_tied": "the sensor's noise and the gyro's over each compared pair"
                 }.get(d.residual, "the sensor's noise")
        return (f"The model {', '.join(d.model)} explains this recording: its field error "
                f"{size} is {noise}. Nothing to do.")
    from .misfit import summary as misfit_lines

    lines = misfit_lines(d.misfit) if d.misfit else []
    where = f" Where it sits: {' '.join(lines[0].split())}." if lines else ""
    judged = d.floor_for(d.residual)
    floor = (f" above the noise floor {judged:.3g} {u}" if np.isfinite(judged)
             else " and the noise floor cannot be measured here")
    return (f"The field error is {size}{floor}, and no catalog effect explains it.{where} "
            "To do: record again away from steel and electronics, or look at the report's "
            "residual-vs-time and sphere pictures for what changed.")
