"""What makes a result a value: deep-frozen contents, array-safe equality and a small escaped
HTML table for Jupyter.

:func:`freeze` turns the plain containers a result holds (lists, dicts, arrays, nested) into
ones that refuse in-place change — tuples, :class:`FrozenDict`, read-only arrays — and
:func:`thaw` gives plain lists and dicts back (for JSON).

:func:`same` compares the contents of results (numbers, arrays, mappings, sequences, nested)
element by element, a NaN equal to a NaN (a "no value" — an unmeasured floor, an unknown rms —
is the same absence on both sides). :func:`html_table` renders rows of label and value cells,
every cell HTML-escaped.
"""
from __future__ import annotations

import dataclasses
import html
import math
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np


class FrozenDict(Mapping):
    """A read-only mapping whose values are frozen (:func:`freeze`) on construction; equal to
    any mapping with the same items (:func:`same`: arrays element-wise, NaN equal to NaN), and
    copied and pickled like a dict (unlike :class:`types.MappingProxyType`)."""

    __slots__ = ("_items",)

    def __init__(self, items: Mapping | Iterable = (), **more):
        object.__setattr__(self, "_items",
                           {k: freeze(v) for k, v in dict(items, **more).items()})

    def __getitem__(self, key):
        return self._items[key]

    def __iter__(self) -> Iterator:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is read-only")

    __delattr__ = __setattr__

    def __eq__(self, other) -> bool:
        if not isinstance(other, Mapping):
            return NotImplemented
        return same(self, other)

    def __reduce__(self):
        return type(self), (self._items,)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._items!r})"

    __hash__ = None   # its values may be unhashable (floats compared NaN-safe, arrays)


def freeze(value: Any) -> Any:
    """``value`` with every container replaced, recursively, by one that refuses in-place
    change: a mapping → :class:`FrozenDict`, a list or tuple → tuple, an array → a read-only
    copy (a read-only array is kept); anything else (numbers, strings, objects) as it is."""
    if isinstance(value, FrozenDict):
        return value
    if isinstance(value, Mapping):
        return FrozenDict(value)
    if isinstance(value, (list, tuple)):
        return tuple(freeze(v) for v in value)
    if isinstance(value, np.ndarray):
        if not value.flags.writeable and value.base is None:
            return value
        value = np.array(value)
        value.flags.writeable = False
    return value


def thaw(value: Any) -> Any:
    """Plain containers of ``value``'s own, recursively: a mapping → dict, a list or tuple →
    list, an array → a writable copy; anything else as it is."""
    if isinstance(value, Mapping):
        return {k: thaw(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [thaw(v) for v in value]
    if isinstance(value, np.ndarray):
        return np.array(value)
    return value


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
