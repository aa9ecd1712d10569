"""pandas' C CSV tokenizer for the plain-number fast path of :mod:`streamcal.inputs.trackio`
(issue #13 item 2: parsing was ~40 % of a long-log diagnosis).

On a 100 000-row, 12-column slice of a simulated track it takes ~0.13 s where
:func:`numpy.loadtxt` (after the empty-cell → ``nan`` rewrite) takes ~1.5–2 s, and returns the
same float64 values bit for bit (``tools/bench_long_diagnose.py``, ``tests/test_fastcsv.py``).
It is used only for text the caller has already restricted to digits, signs, dots, exponents,
commas and newlines (no blanks: a blank-only cell is left to the checking path), only above
:data:`MIN_BYTES` (importing pandas costs ~0.5–1 s), and only when pandas is installed; every
row must have exactly the header's number of cells (pandas would pad a short row with NaN
where the checking path reports it), anything pandas rejects returns None and the caller's
checking path decides, so errors keep naming line and column.
"""
from __future__ import annotations

import io

import numpy as np

#: Texts shorter than this (bytes) keep numpy's parser: the pandas import would cost more.
MIN_BYTES = 2 << 20

_pandas = None


def _load_pandas():
    global _pandas
    if _pandas is None:
        try:
            import pandas
        except ImportError:   # an installation without it keeps numpy's parser
            pandas = False
        _pandas = pandas
    return _pandas


def parse_plain(data: bytes, nrow: int, ncol: int, min_bytes: int | None = None):
    """(nrow, ncol) float64 values of the comma-separated ``data`` (its bytes only digits,
    ``eE.+-``, commas and newlines; no blank or comment lines), NaN for empty cells; None when
    pandas is not there, ``data`` is below ``min_bytes`` (default :data:`MIN_BYTES`), a row
    has another number of cells than ``ncol``, or a cell is not a number."""
    if len(data) < (MIN_BYTES if min_bytes is None else min_bytes) or b" " in data \
            or b"\t" in data:
        return None
    pd = _load_pandas()
    if not pd:
        return None
    # every row holds ncol cells iff the separators (commas, newlines) number nrow·ncol (the
    # last newline may be missing) and every ncol-th of them is a newline
    raw = np.frombuffer(data, dtype=np.uint8)
    sep = raw[(raw == 44) | (raw == 10)]
    if len(sep) != nrow * ncol - (not data.endswith(b"\n")) or \
            np.any(sep[ncol - 1::ncol] != 10):
        return None
    try:
        frame = pd.read_csv(io.BytesIO(data), header=None, names=range(ncol), dtype=np.float64,
                            engine="c", skip_blank_lines=False, keep_default_na=False,
                            na_values=[""])
    except (ValueError, pd.errors.ParserError):
        return None
    values = frame.to_numpy(dtype=np.float64)
    return values if values.shape == (nrow, ncol) else None
