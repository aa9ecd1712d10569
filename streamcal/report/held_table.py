"""HTML of a diagnosis against a given calibration (issue #10): where the calibration came from
and, for each core parameter, whether this recording re-estimated it or held it at the given
value, with its value, its σ and the Cramér–Rao error that decided (sensor unit)."""
from __future__ import annotations

import html

import numpy as np

from ..fitting.entries import B_INDEX, B_PARAMS, K_INDEX, K_PARAMS, RADIUS, entry


def _num(v, fmt: str = ".4g") -> str:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return "–"
    return format(v, fmt) if np.isfinite(v) else "–"


def held_section(d, unit: str) -> str:
    """The section, or "" for a fresh diagnosis (``held`` None)."""
    h = d.held
    if h is None or d.calibration is None:
        return ""
    e = html.escape
    rows = []
    after = {a["parameter"]: a for a in h.held_after_fit}
    radius = [RADIUS] if (RADIUS in h.parameters or RADIUS in h.estimated
                          or RADIUS in h.predicted_sigma) else []
    for name in [*(n for n, _ in (*K_PARAMS, *B_PARAMS)), *radius]:
        pin = h.gyro_pinned.get(name)
        est = h.estimated.get(name) or pin
        status = "pinned by the gyro link" if pin else "re-estimated" if est else (
            "held after the fit" if name in after else "held")
        value = est["value"] if est else entry(d.calibration.K, d.calibration.b, name)
        sigma = _num(est["sigma"]) if est else "–"
        rows.append((name, status, _num(value), sigma, _num(h.predicted_sigma.get(name)), unit))
    rows += [(e(n), "held", "as in the calibration", "–", "–", "") for n in h.parameters
             if n not in K_INDEX and n not in B_INDEX and n != RADIUS]
    head = "".join(f"<th>{h}</th>" for h in ("parameter", "status", "value", "σ (this recording)",
                                             "predicted σ (Cramér–Rao)", "unit"))
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    n_r = h.n_ranked or d.n
    used = h.attitude_reference
    joint = (f" Every held fit here also fitted the field's direction against the attitude "
             f"reference ({used['samples']} samples, width {used['width_deg']:.2g}°), beside its "
             f"size; the field errors shown are the size's. Caveat: {e(str(used['caveat']))}"
             if used else "")
    ranked = (f" The candidate refits used {n_r} of the {d.n} samples (every cell of direction "
              f"× stretch of time kept); the model's rms and these parameters use all {d.n}."
              if n_r < d.n else "")
    return (f'<h2 id="held">Diagnosed against a given calibration</h2>'
            f"<p>Calibration: <b>{e(str(h.calibration_source))}</b>. A parameter is re-estimated "
            f"from this recording when its predicted (Cramér–Rao) error is below "
            f"{_num(h.tolerance, '.3g')} {e(unit)} (0.5 % of the field radius), else held at the "
            f"calibration's value. After the fit the rule is checked again at the fitted point "
            f"(σ within the tolerance, value within its plausible range ± 3 σ); the worst "
            f"failing parameter is held and the fit repeated ({len(after)} held so)."
            f"{_status(d)}{ranked}{joint}</p>"
            f'<table id="held-parameters"><thead><tr>{head}</tr></thead><tbody>{body}</tbody>'
            f"</table>")


def _status(d) -> str:
    st = d.held.fit_status
    return (f" The held fit ended <b>{html.escape(st['status'])}</b> after {st['iterations']} "
            f"iterations." if st else "")
