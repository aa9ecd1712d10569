"""C header for the Arduino sketch's initial calibration (``ScCal``: K upper triangular
row-major ``{k11, k12, k13, k22, k23, k33}`` and ``b``, float literals in µT).

This is streamcal's own model, so K and b go across unchanged; effects beyond them are listed
as not expressed.
"""
from __future__ import annotations

from ..calibration import Calibration
from ..units import display_unit, effect_params
from .common import CORE

GUARD = "SC_INITIAL_CAL_H"


def _c_float(value: float) -> str:
    text = f"{float(value):.9g}"
    if "e" not in text and "." not in text and "inf" not in text and "nan" not in text:
        text += ".0"
    return text + "f"


def export(cal: Calibration) -> tuple[str, list[str]]:
    if cal.sensor != "mag":
        from ..errors import InputError

        raise InputError(f"export: c-header carries a magnetometer calibration, this one is "
                         f"for {cal.sensor!r}")
    notes = [f"{name}: {effect_params(name, params, cal.unit, digits=4)}"
             for name, params in cal.effects.items()]
    notes += [f"{name} (in the model)" for name in cal.model
              if name not in CORE and name not in cal.effects]
    if cal.unit != "uT":
        notes.append(f"values are in {display_unit(cal.unit) or 'an unknown unit'}, not µT")
    K, b = cal.K, cal.b
    k = [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], K[2, 2]]
    lines = [f"/* streamcal initial calibration ({cal.created}): m = K x + b, uT;",
             "   K upper triangular, row-major {k11, k12, k13, k22, k23, k33}. */"]
    lines += [f"/* NOT EXPRESSED: {note} */" for note in notes]
    lines += [f"#ifndef {GUARD}", f"#define {GUARD}",
              f"#define SC_INITIAL_CAL_K {{{', '.join(_c_float(v) for v in k)}}}",
              f"#define SC_INITIAL_CAL_B {{{', '.join(_c_float(v) for v in b)}}}",
              f"#endif /* {GUARD} */"]
    return "\n".join(lines) + "\n", notes
