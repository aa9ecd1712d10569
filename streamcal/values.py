"""What makes a result a value: array-safe equality and a small escaped HTML table for Jupyter.

:func:`same` compares the contents of results (numbers, arrays, mappings, sequences, nested)
element by element, a NaN equal to a NaN (a "no value" — an unmeasured floor, an unknown rms —
is the same absence on both sides). :func:`html_table` renders rows of label and value cells,
every cell HTML-escaped.
"""
from __future__ import annotations

import dataclasses
import html
import math
from typing import Any, Iterable, Mapping, Sequence

import numpy as np


def same(a: Any, b: Any) -> bool:
    """True when ``a`` and ``b`` hold equal contents: arrays (and a list against an array)
    element-wise with equal shapes, floats with NaN equal to NaN, mappings key by key,
    sequences item by item; other objects by ``==``."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        try:
            x, y = np.asarray(a), np.asarray(b)
        except (TypeError, ValueError):
            return False
        if x.shape != y.shape:
            return False
        if x.dtype.kind in "fc" or y.dtype.kind in "fc":
            return bool(np.array_equal(x, y, equal_nan=True))
        if x.dtype == object or y.dtype == object:
            return all(same(p, q) for p, q in zip(x.ravel(), y.ravel()))
        return bool(np.array_equal(x, y))
    if isinstance(a, Mapping) or isinstance(b, Mapping):
        if not (isinstance(a, Mapping) and isinstance(b, Mapping)) or a.keys() != b.keys():
            return False
        return all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        if not (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple))) or \
                len(a) != len(b):
            return False
        return all(same(p, q) for p, q in zip(a, b))
    if _is_real(a) and _is_real(b):
        x, y = float(a), float(b)
        return x == y or (math.isnan(x) and math.isnan(y))
    return bool(a == b)


def _is_real(v) -> bool:
    return isinstance(v, (float, int, np.floating, np.integer)) and not isinstance(v, bool)


def fields_equal(a, b) -> bool:
    """Two dataclass instances of one type with :func:`same` values in every field declared
    with ``compare=True``."""
    return type(a) is type(b) and all(
        same(getattr(a, f.name), getattr(b, f.name))
        for f in dataclasses.fields(a) if f.compare)


def html_table(rows: Iterable[Sequence[Any]], *, header: Sequence[str] | None = None,
               caption: str | None = None) -> str:
    """An HTML ``<table>`` of ``rows`` (each a sequence of cells, shown with ``str``); the first
    cell of a row without a ``header`` is a row label (``<th>``). Every cell is escaped."""
    out = ["<table>"]
    if caption:
        out.append(f"<caption>{html.escape(caption)}</caption>")
    if header:
        out.append("<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>")
    for row in rows:
        cells = [html.escape(str(c)) for c in row]
        if header is None and cells:
            out.append(f"<tr><th>{cells[0]}</th>" + "".join(f"<td>{c}</td>" for c in cells[1:])
                       + "</tr>")
        else:
            out.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    out.append("</table>")
    return "".join(out)
