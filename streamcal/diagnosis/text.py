"""The short summary ``print(diagnosis)`` shows: verdict, rms beside the noise floor, the
top candidates (the full result is :meth:`~streamcal.diagnosis.result.Diagnosis.to_dict`;
the command line's tables are in :mod:`streamcal.cli.diagnose`)."""
from __future__ import annotations

import math

from ..units import quantity

#: Candidates shown in the summary.
TOP = 3


def diagnosis_unit(d) -> str:
    """Sensor unit of a diagnosis's rms values (its calibration's, else its ``unit``, else µT)."""
    cal = getattr(d, "calibration", None)
    return getattr(cal, "unit", None) or getattr(d, "unit", None) or "uT"


def _residual(name: str) -> str:
    return name.replace("_", "-")


def summary(d, top: int = TOP) -> str:
    """A few lines: verdict, the rms on its residual against the noise floor, outliers and the
    ``top`` ranked candidates, each ``rms_after`` beside the rms without it on the same
    residual."""
    u = diagnosis_unit(d)
    judged = d.floor_for(d.residual)
    if d.residual != "sensor":
        floor = (f"its own floor {quantity(judged, u, 4)} ({d.rms / judged:.2f}× the floor)"
                 if math.isfinite(judged) and judged > 0 else "its own floor not measurable")
    elif d.floor_known:
        floor = f"noise floor {quantity(d.noise_floor, u, 4)}"
        if d.noise_floor > 0:
            floor += f" ({d.rms / d.noise_floor:.2f}× the floor)"
    else:
        floor = "noise floor not measurable"
    lines = [f"Diagnosis: {d.verdict}",
             f"  model      {', '.join(d.model)}",
             f"  rms        {quantity(d.rms, u, 4)} on the {_residual(d.residual)} residual; "
             f"{floor}",
             f"  samples    {d.n} ({d.n_outliers} outliers)"]
    if d.candidates:
        lines.append(f"  candidates (of {len(d.candidates)}, best first):")
        for c in d.candidates[:top]:
            residual, before = d.baseline(c)
            p = f"p {c.p_value:.2g}" if c.p_value is not None and math.isfinite(c.p_value) \
                else "p –"
            lines.append(f"    {c.effect:<24} {quantity(before, u, 4)} → "
                         f"{quantity(c.rms_after, u, 4)} ({_residual(residual)}, {p})")
    return "\n".join(lines)


def short_repr(d) -> str:
    """One line: ``<Diagnosis effect_missing: rms 1.23 µT (sensor), top temperature_offset>``."""
    u = diagnosis_unit(d)
    top = f", top {d.candidates[0].effect}" if d.candidates else ""
    return (f"<{type(d).__name__} {d.verdict}: rms {quantity(d.rms, u, 4)} ({d.residual}), "
            f"n={d.n}{top}>")
