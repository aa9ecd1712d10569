"""The HTML report: one self-contained page (figures inline as base64 PNG, no external
resources, no timestamps) saying what the model misses, with the figures of
:mod:`streamcal.report.figures` and tables of the candidates, the model ladder and the
calibration parameters with their units.

A small inline script sets ``data-images="loaded"`` on ``<body>`` once every image has decoded
(``img.complete && img.naturalWidth > 0``), or ``data-images="broken"``: the browser test reads it.
"""
from __future__ import annotations

import base64
import html
import os
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from .figure_common import RenderedFigure
from .figure_data import FigureData, unit_label
from .figures import render_figures
from .figures_ladder import RESIDUAL_FAMILIES, ladder_steps, relative_change

_CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;max-width:1240px;margin:0 auto;
padding:16px 24px;color:#222;line-height:1.45}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
.sub{color:#666;margin-top:0}.box{padding:10px 14px;border-radius:6px;margin:12px 0}
.missing{background:#fff4e5;border:1px solid #f0b35a}.floor{background:#eaf7ea;border:1px solid #7cc47c}
.refused{background:#fdecec;border:1px solid #e08080}
table{border-collapse:collapse;margin:8px 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f3f3f3}td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:14px 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{color:#555;font-size:.92em}code{background:#f3f3f3;padding:1px 4px;border-radius:3px}
"""

_SCRIPT = """
(function(){
  function check(){
    var imgs=document.images, ok=true;
    for(var i=0;i<imgs.length;i++){
      if(!imgs[i].complete){return false;}
      if(!(imgs[i].naturalWidth>0)){ok=false;}
    }
    document.body.setAttribute('data-images', ok ? 'loaded' : 'broken');
    document.body.setAttribute('data-image-count', String(imgs.length));
    return true;
  }
  function poll(){ if(!check()){ setTimeout(poll, 20); } }
  if(document.readyState==='complete'){poll();}else{window.addEventListener('load', poll);}
})();
"""

def _param_cells(effect: str, key: str, value, unit: str) -> tuple[str, str]:
    """(value, unit) cells of an effect parameter: the units and scaling of
    :mod:`streamcal.units` (seconds as ms/µs, radians as degrees), 4 significant digits, and
    what the number means when the effect declares it (its ``notes``)."""
    from ..model.catalog import BY_NAME
    from ..units import param_unit, scaled

    try:
        values, shown = scaled(value, param_unit(effect, key, unit))
    except (TypeError, ValueError):
        return _e(value), ""
    info = BY_NAME.get(effect)
    note = info.notes.get(key) if info is not None else None
    shown = f"{shown} ({note})" if note and shown else (note or shown)
    return (_vec(values) if np.ndim(values) else _num(values)), _e(shown)


def _e(value) -> str:
    return html.escape(str(value), quote=True)


def _num(value, fmt: str = ".4g") -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return _e(value)
    return format(v, fmt) if np.isfinite(v) else "–"


def _vec(values, fmt: str = ".4g") -> str:
    return "[" + ", ".join(_num(v, fmt) for v in np.ravel(values)) + "]"


def _table(header, rows, numeric=()) -> str:
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(
        f'<td class="num">{c}</td>' if k in numeric else f"<td>{c}</td>" for k, c in enumerate(r))
        + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _img(fig: RenderedFigure) -> str:
    data = base64.b64encode(fig.png).decode("ascii")
    return (f'<figure id="fig-{_e(fig.name)}"><h3>{_e(fig.title)}</h3>'
            f'<img src="data:image/png;base64,{data}" alt="{_e(fig.title)}">'
            f"<figcaption>{_e(fig.caption)}</figcaption></figure>")


def _residual_name(residual: str) -> str:
    label, what, _, _ = RESIDUAL_FAMILIES.get(residual, RESIDUAL_FAMILIES["sensor"])
    return f"{label} ({what})"


def _u(unit: str) -> str:
    """`` µT`` after a number in prose; nothing for an unknown unit (said once, at the top)."""
    return f" {unit}" if unit else ""


def _floor_text(d, unit: str) -> str:
    """"x× the noise floor (f unit)", or why there is no floor to compare with; a rms on a tied
    residual against that residual's own floor."""
    if d.residual != "sensor":
        floor = d.floor_for(d.residual)
        name = d.residual.replace("_", "-")
        if not np.isfinite(floor):
            entry = (d.tied_noise_floors or {}).get(d.residual) or {}
            return (f"the {name} residual's floor cannot be measured from this recording "
                    f"({_e(entry.get('reason') or d.noise_floor_reason)})")
        return (f"{_num(d.rms / floor, '.2f')}× the {name} residual's own noise floor "
                f"({_num(floor)}{_u(unit)})")
    if not d.floor_known:
        return (f"the noise floor cannot be measured from this recording "
                f"({_e(d.noise_floor_reason)})")
    return (f"{_num(d.rms / d.noise_floor, '.2f')}× the noise floor "
            f"({_num(d.noise_floor)}{_u(unit)})")


def _misfit(d) -> str:
    from ..diagnosis.misfit import summary

    lines = summary(d.misfit or {})
    if not lines:
        return ""
    return ("<p>Where the misfit sits (share of the residual energy against share of the "
            "samples):</p><ul>" + "".join(f"<li>{_e(' '.join(line.split()))}</li>"
                                          for line in lines) + "</ul>")


_HEADLINES = {"effect_missing": "An effect is missing.",
              "unexplained": "The misfit is not explained.",
              "at_noise_floor": "The model is at the noise floor."}


def _summary(d, unit: str) -> str:
    """The diagnosis' own plain sentences and the command they advise (the same words as the
    command line's), with the rule its verdict follows."""
    import shlex

    cmd = " ".join(d.next_step) if d.next_step else ""
    text = d.summary.replace(f" To do: {cmd}", "") if cmd else d.summary
    rule = d.significance_rule if d.verdict == "effect_missing" else d.noise_floor_rule
    todo = (f"<br>Next step (gives the rms promised): "
            f"<code>{_e(' '.join(shlex.quote(w) for w in d.next_step))}</code>" if cmd else "")
    box = "floor" if d.verdict == "at_noise_floor" else "missing"
    return (f'<div class="box {box}"><b>{_e(_HEADLINES.get(d.verdict, d.verdict))}</b> '
            f"{_e(text)}{todo}<br><span class=\"sub\">Verdict {_e(d.verdict)}; rule: "
            f"{_e(rule)}.</span>{_misfit(d) if d.verdict == 'unexplained' else ''}</div>")


def _heading_error(d) -> str:
    """The heading error the ladder's first and last rms imply (``heading_error_deg``), or why
    it is unknown."""
    h = d.heading_error_deg or {}
    if h.get("before") is None:
        return (f'<p class="heading-error">Heading error: unknown '
                f"({_e(d.heading_error_reason or 'no horizontal field')}).</p>")
    after = "" if h.get("after") is None or h["after"] == h["before"] else \
        f" → {_num(h['after'], '.2f')}° with the ladder's last model"
    return (f'<p class="heading-error">Heading error: up to {_num(h["before"], ".2f")}° with '
            f"the model as given{after} (horizontal field {_num(h['H_uT'], '.3g')} µT; "
            f"{_e(h.get('rule', ''))}).</p>")


def diagnosis_section(d, unit: str, *, title: str, anchor: str, reason: str | None = None) -> str:
    """One diagnosis as a section of a page of several (``report --compass all``): its verdict
    and plain sentences, the heading error and the model ladder (``d`` None: ``reason``, why
    there is none). ``unit``: the track's unit label (:func:`.figure_data.unit_label`)."""
    head = f'<section id="{_e(anchor)}"><h2>{_e(title)}</h2>'
    if d is None:
        return (head + f'<div class="box refused"><b>No calibration.</b> '
                f"{_e(reason or 'unknown reason')}</div></section>")
    shown = "" if unit == "unit unknown" else unit
    return (head + _summary(d, shown) + _heading_error(d) + "<h3>Model ladder</h3>"
            + _ladder(d, unit) + "</section>")


def _floor_ratio(rms: float, residual: str, d) -> str:
    """× the noise floor of the residual the rms is on (the magnetometer's for the sensor
    residual, a tied residual's own for a tied one), where that floor was measured."""
    floor = d.floor_for(residual)
    return _num(rms / floor, ".2f") if np.isfinite(floor) and floor > 0 else "–"


_SCALES_NOTE = ("<p class=\"sub\">Each rms is on the residual named in its row, and is compared "
                "with the rms before on that same residual. The sensor residual (the autocalibration "
                "paper's estimation error) is the "
                "reading's distance to the fitted surface with every direction free; "
                "misalignment and lag leave no trace there, so they are measured on the "
                "gravity-tied residual (each direction tied to the accelerometer's gravity, "
                "whose own error adds to it: noise alone gives about √2× the floor) or the "
                "gyro-tied one (each direction carried 0.5 s ahead by the gyro: about 2× the "
                "floor). Rows on those residuals have no “× floor”.</p>")


def _candidates(d, unit: str) -> str:
    if not d.candidates:
        return "<p>No candidate effect could be tried: the track has no column they need, or " \
               "the model already holds them.</p>"
    rows = []
    for c in d.candidates:
        row = d.candidate_dict(c)
        residual, before = row["residual"], row["rms_before"]
        ratio = (_floor_ratio(c.rms_after, residual, d),) if d.floor_known else ()
        rows.append((_e(c.effect), _e(RESIDUAL_FAMILIES.get(residual, ("?",))[0]), _num(before),
                     _num(c.rms_after), _e(relative_change(before, c.rms_after)), *ratio,
                     _num(c.p_value, ".2e"), "yes" if row["significant"] else "no",
                     "yes" if row["material"] else "no", _e(c.evidence)))
    head = ("effect", "residual", f"rms before ({unit})", f"rms after ({unit})", "change",
            *(("× floor",) if d.floor_known else ()), "p-value", "significant", "material",
            "evidence")
    table = _table(head, rows, numeric=tuple(range(2, 7 if d.floor_known else 6)))
    mixed = any(d.baseline(c)[0] != "sensor" for c in d.candidates)
    rule = f'<p class="sub">Rule: {_e(d.significance_rule)}; an effect is missing only when both hold.</p>'
    return table + rule + (_SCALES_NOTE if mixed else "")


def _ladder(d, unit: str) -> str:
    rows = []
    steps = ladder_steps(d)
    for step in steps:
        name = "+ " + step["added"] if "added" in step else ", ".join(step["model"])
        before = step.get("rms_before")
        rows.append((_e(name), _e(RESIDUAL_FAMILIES[step["residual"]][0]),
                     _num(before) if before is not None else "",
                     _num(step["rms"]),
                     _e(relative_change(before, step["rms"])) if before is not None else "",
                     *((_floor_ratio(step["rms"], step["residual"], d),)
                       if d.floor_known else ()),
                     _num(step.get("p_value"), ".2e") if "p_value" in step else ""))
    if d.floor_known:
        rows.append(("noise floor", "sensor residual", "", _num(d.noise_floor), "", "1.00", ""))
        for residual in d.tied_noise_floors or {}:
            if np.isfinite(d.floor_for(residual)):
                rows.append(("noise floor", _e(residual.replace("_", "-") + " residual"), "",
                             _num(d.floor_for(residual)), "", "1.00", ""))
    table = _table(("step", "residual", f"rms before ({unit})", f"rms ({unit})", "change",
                    *(("× floor",) if d.floor_known else ()), "p-value"), rows,
                   numeric=tuple(range(2, 7 if d.floor_known else 6)))
    mixed = any(s["residual"] != "sensor" for s in steps)
    # the note is given once: under the candidates when they already mix residuals
    said = any(d.baseline(c)[0] != "sensor" for c in d.candidates)
    return table + (_SCALES_NOTE if mixed and not said else "")


def _parameters(cal, unit: str) -> str:
    K = np.asarray(cal.K)
    rows = [("model", _e(", ".join(cal.model)), ""), ("method / kernel",
             _e(f"{cal.method} / {cal.kernel or '–'}"), "")]
    rows += [(f"K row {i + 1}", _vec(K[i]), unit) for i in range(3)]
    rows += [("b (hard iron)", _vec(cal.b), unit)]
    for effect, params in (cal.effects or {}).items():
        for key, value in (params or {}).items():
            if key == "channels" and isinstance(value, dict):
                for ch, p in value.items():
                    for k2, v2 in p.items():
                        rows.append((_e(f"{effect}: {ch}.{k2}"),
                                     *_param_cells(effect, k2, v2, unit)))
                continue
            rows.append((_e(f"{effect}: {key}"), *_param_cells(effect, key, value, unit)))
    from ..diagnosis.scales import calibration_residual

    label = RESIDUAL_FAMILIES[calibration_residual(cal)][0]
    rows += [("field strength", _num(cal.field), unit),
             (_e(f"rms on the {label} (inliers)"), _num(cal.rms), unit),
             ("samples / outliers of this fit", f"{cal.n} / {cal.n_outliers}", "")]
    return _table(("parameter", "value", "unit"), rows)


def _noise(d, unit: str) -> str:
    n = d.noise or {}
    floor = (_num(d.noise_floor) if d.floor_known
             else "not measurable: " + _e(d.noise_floor_reason))
    rows = [("noise floor", floor, unit if d.floor_known else ""),
            ("σ per axis", _vec(n.get("sigma_axes", [])), unit),
            ("quantization step (LSB) per axis", _vec(n.get("lsb", [])), unit),
            ("estimated by", _e(n.get("method", "")), ""), ("samples used", _e(n.get("n_used", "")), "")]
    for residual, entry in (d.tied_noise_floors or {}).items():
        name = residual.replace("_", "-")
        if entry.get("reliable"):
            rows += [(f"{name} residual's floor", _num(entry["floor"]), unit),
                     ("  magnetometer noise it keeps", _num(entry["magnetometer_part"]), unit),
                     ("  its reference's error", _num(entry["reference_part"]), unit),
                     ("  reference estimated from", _e(entry.get("method", "")), "")]
        else:
            rows.append((f"{name} residual's floor",
                         "not measurable: " + _e(entry.get("reason", "")), ""))
    return _table(("", "value", "unit"), rows)


def _metadata(track) -> str:
    keep = [(k, v) for k, v in track.metadata.items() if k in _SHOWN_METADATA]
    return "".join(f'<p class="sub">{_e(k)}: {_e(v)}</p>' for k, v in keep)


_SHOWN_METADATA = ("sensor", "source", "origin", "description")


def render_html(track, diagnosis=None, *, reason: str | None = None, title: str | None = None,
                figures: list[RenderedFigure] | None = None, intro: str = "",
                name: str | None = None) -> str:
    """The report page as a string.

    Args:
        track: the :class:`streamcal.inputs.track.Track` diagnosed.
        diagnosis: its :class:`~streamcal.diagnose.Diagnosis`, or None when the fit refused the
            track; ``reason`` then says why, and the page shows what needs no calibration.
        title: page title (default: the track's name).
        figures: already rendered figures (default: rendered here).
        intro: extra HTML placed under the title (e.g. the demo's streaming summary).
        name: how to call the track file in the text (default: its file name).
    """
    data = None
    if figures is None:
        data = FigureData.build(track, diagnosis, reason)
        figures = render_figures(data)
    if name is None:
        name = track.path.name if getattr(track, "path", None) else "track.csv"
    unit = unit_label(track.mag_unit)              # tables and headers: "unit unknown" if so
    shown = "" if unit == "unit unknown" else unit  # prose: no unit after a number then
    title = title or f"streamcal report: {name}"
    parts = [f"<h1>{_e(title)}</h1>",
             f'<p class="sub">{len(track.t_mag)} magnetometer samples over '
             f"{_num(track.t[-1] - track.t[0] if len(track) else 0, '.1f')} s, unit {_e(shown or 'unknown')}; "
             f"columns {_e(', '.join(track.columns))}</p>", _metadata(track), intro]
    if diagnosis is None:
        parts.append(f'<div class="box refused"><b>No calibration: the fit refused this track.'
                     f"</b> {_e(reason or 'unknown reason')}<br>The figures below show what needs "
                     f"no calibration: the raw readings, their magnitude and the directions "
                     f"seen from the centre of a one-pass sphere fit.</div>")
    else:
        parts += [_summary(diagnosis, shown), _heading_error(diagnosis)]
        if diagnosis.outlier_spans:
            spans = ", ".join(f"{a:.2f}–{b:.2f} s" for a, b in diagnosis.outlier_spans)
            last = diagnosis.ladder[-1] if diagnosis.ladder else {}
            n_last = last.get("n_outliers", diagnosis.n_outliers)
            of = "" if len(diagnosis.ladder) < 2 else (
                f" of the last model of the ladder, <code>{_e(', '.join(last['model']))}</code> "
                f"({diagnosis.n_outliers} of the model as given: its missing effects push "
                f"samples out)")
            parts.append(f"<p><b>{n_last}</b> of {diagnosis.n} samples are "
                         f"outliers{of}; they cluster in {_e(spans)}.</p>")
    parts += [_img(f) for f in figures]
    if data is not None and diagnosis is not None:
        from .figures_aux import aux_residual_figure

        aux = aux_residual_figure(track, diagnosis)
        parts += [_img(aux)] if aux is not None else []
    if data is not None:
        from .figures_attitude import attitude_reference_figure

        att = attitude_reference_figure(track)
        parts += [_img(att)] if att is not None else []
    if diagnosis is not None:
        from .held_table import held_section

        parts.append(held_section(diagnosis, unit))
        parts += ["<h2>Candidate effects</h2>", _candidates(diagnosis, unit),
                  "<h2>Model ladder</h2>", _ladder(diagnosis, unit),
                  "<h2>Calibration of the model as given</h2>",
                  _parameters(diagnosis.calibration, unit)]
        added = [c for c in diagnosis.candidates
                 if c.effect in {s.get("added") for s in diagnosis.ladder[1:]}]
        last = max(added, key=lambda c: len(c.calibration.model), default=None) \
            if added else None
        if last is not None and last.calibration is not None:
            names = ", ".join(s["added"] for s in diagnosis.ladder[1:])
            parts += [f"<h2>Calibration with {_e(names)} added (what the next step gives)</h2>",
                      _parameters(last.calibration, unit)]
        parts += ["<h2>Noise floor</h2>", _noise(diagnosis, unit)]
    from .. import __version__

    body = "\n".join(p for p in parts if p)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"generator\" content=\"streamcal {_e(__version__)}\">"
            f"<title>{_e(title)}</title><style>{_CSS}</style></head>\n<body>\n{body}\n"
            f"<p class=\"sub\">made by streamcal {_e(__version__)}</p>\n"
            f"<script>{_SCRIPT}</script>\n</body></html>\n")


def write_report(path: str | os.PathLike, track, diagnosis=None, **kwargs) -> Path:
    """Write :func:`render_html` atomically to ``path``; returns the path."""
    path = Path(path)
    atomic_write_text(path, render_html(track, diagnosis, **kwargs), mode=0o644)
    return path
