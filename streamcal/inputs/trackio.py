"""Track files on disk (docs/tracks_and_inputs.md): parse CSV / CSV.gz into columns, format
columns back to CSV.

Parsing is columnar. The fast path hands the whole data section to :func:`numpy.loadtxt` (its C
tokenizer) after empty cells have been turned into ``nan``; that is only sound when the data
section holds nothing but digits, signs, dots, exponents, commas and blanks, because then every
NaN it returns came from an empty cell. Anything else (a word, a quote, ``nan``, a non-UTF-8
byte, a wrong cell count, an overflow to inf) sends the file to the slow path, which checks every
cell against :data:`NUMBER` and names the first bad cell of each row by physical line and column.
Both paths yield the same numbers for the same clean input (tested).

Line numbers are 1-based physical lines of the decompressed text, metadata lines included.
"""
from __future__ import annotations

import gzip
import io
import os
import re
import zlib
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes
from ..errors import TrackError
from .fastcsv import parse_plain

TIME = "t"
MAG = ("mx", "my", "mz")
ACCEL = ("ax", "ay", "az")
GYRO = ("gx", "gy", "gz")
TEMP = "temp"
TRIPLES = {"mag": MAG, "accel": ACCEL, "gyro": GYRO}
KNOWN = frozenset((TIME, TEMP) + MAG + ACCEL + GYRO)
VERSION_KEY = "streamcal-track"
VERSION = "1"

#: A numeric cell (after stripping blanks): decimal, optional exponent; no nan/inf words,
#: no underscores, no hex, ASCII digits only.
NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
#: Column names: an identifier, also allowing '.' and '-' after the first character.
COLUMN_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*")
# Fast-path scans, each a single C pass (bytes.translate, regexes with a literal first byte).
_PLAIN = b"0123456789eE.,+- \t\n"  # the only bytes the fast path accepts
_EMPTY_CELL = re.compile(rb",[,\n]")
_EMPTY_FIRST_CELL = re.compile(rb"\n,")
_SUSPECT_START = "\n#\r \t"  # a line starting so may be blank or a comment
_SUSPECT_LINE = re.compile("\n[\n#\r \t]")
_GZIP_MAGIC = b"\x1f\x8b"
_UNDECODED = re.compile("[\udc80-\udcff]")  # bytes kept by errors="surrogateescape"
_NON_FINITE_WORDS = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity",
                     "-infinity"}
MAX_REASONS = 10


class Parsed:
    """What :func:`read` found: columns in file order, metadata, per-row line numbers, skips."""

    def __init__(self, columns, metadata, lines, skipped_rows, skip_reasons):
        self.columns, self.metadata, self.lines = columns, metadata, lines
        self.skipped_rows, self.skip_reasons = skipped_rows, skip_reasons


# ----------------------------------------------------------------------------- bytes → text


def _load_bytes(path: str) -> bytes:
    try:
        with open(path, "rb") as handle:
            raw = handle.read()
    except OSError as exc:
        raise TrackError(f"cannot read the file: {exc.strerror or exc}", path) from None
    if raw[:2] != _GZIP_MAGIC:
        return raw
    try:
        return gzip.decompress(raw)
    except EOFError:
        raise TrackError("gzip stream ends early (truncated or damaged file)", path) from None
    except (OSError, zlib.error, ValueError) as exc:
        raise TrackError(f"damaged gzip file: {exc}", path) from None


def _decode(raw: bytes) -> str:
    """UTF-8 text; undecodable bytes survive as lone surrogates so they can be located by line."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("utf-8", errors="surrogateescape")
    if text.startswith("\ufeff"):
        text = text[1:]
    return text.replace("\r\n", "\n")


def _bad_byte(line: str) -> str | None:
    """Describe the first undecodable byte of ``line`` (1-based byte offset), or None."""
    found = _UNDECODED.search(line)
    if found is None:
        return None
    offset = len(line[:found.start()].encode("utf-8", errors="surrogateescape")) + 1
    return f"not UTF-8: byte 0x{ord(found.group()) - 0xdc00:02x} at byte {offset} of the line"


def _has_bad_bytes(text: str) -> bool:
    return not text.isascii() and _UNDECODED.search(text) is not None


# ----------------------------------------------------------------------------- metadata, header


def _split_preamble(text: str, path: str):
    """Return (metadata dict, header line index (0-based), header cells, body text)."""
    metadata: dict[str, str] = {}
    pos, index = 0, 0
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        line = text[pos:end]
        stripped = line.strip(" \t\r")
        if stripped and not stripped.startswith("#"):
            if _has_bad_bytes(line):
                raise TrackError(_bad_byte(line), path, index + 1)
            return metadata, index, line, text[end + 1:]
        if stripped.startswith("#"):
            if _has_bad_bytes(line):
                raise TrackError(_bad_byte(line), path, index + 1)
            key, colon, value = stripped[1:].partition(":")
            if colon and key.strip():
                metadata[key.strip()] = value.strip()
        pos, index = end + 1, index + 1
    if not text.strip(" \t\r\n"):
        raise TrackError("empty file", path)
    raise TrackError("no header row (only '#' metadata lines)", path)


def _parse_header(line: str, line_no: int, path: str) -> list[str]:
    names = [cell.strip().strip('"').strip() for cell in line.split(",")]
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not name:
            raise TrackError(f"empty column name in the header (cell {i + 1}; trailing comma?)",
                             path, line_no)
        if not COLUMN_NAME.fullmatch(name):
            hint = " — the first line after the metadata must be the header, e.g. t,mx,my,mz" \
                if NUMBER.fullmatch(name) else ""
            raise TrackError(f"invalid column name {name!r}: expected letters, digits, '_', "
                             f"'.', '-' starting with a letter{hint}", path, line_no, name)
        if name in seen:
            raise TrackError("duplicate column name", path, line_no, name)
        seen.add(name)
    missing = [name for name in (TIME,) + MAG if name not in seen]
    if missing:
        folded = {n.lower(): n for n in names}
        hints = [f"{folded[m]!r}" for m in missing if m in folded]
        hint = f" (column names are case-sensitive: found {', '.join(hints)})" if hints else ""
        raise TrackError(f"missing required column(s) {', '.join(missing)}; the header has "
                         f"{', '.join(names)}{hint}", path, line_no, missing[0])
    for kind, triple in TRIPLES.items():
        present = [n for n in triple if n in seen]
        if present and len(present) < 3:
            absent = [n for n in triple if n not in seen]
            raise TrackError(f"{kind} columns come in threes: has {', '.join(present)} but not "
                             f"{', '.join(absent)}", path, line_no, absent[0])
    return names


# ----------------------------------------------------------------------------- cells → numbers


def _body_lines(body: str, first_line: int):
    """The data section without blank/comment lines: its text, the physical line number of
    each row, and its lines (None when the text needs no filtering: split later if needed)."""
    # drop blank lines at the end, but not the last line's own trailing blanks: a row reads the
    # same whether it ends the file or a chunk of it
    end = body.find("\n", len(body.rstrip("\n \t\r")))
    body = body[:end] if end != -1 else body
    if not body.strip("\n \t\r"):
        return "", np.zeros(0, dtype=np.int64), []
    if body[0] not in _SUSPECT_START and not _SUSPECT_LINE.search(body):
        count = body.count("\n") + 1
        return body, np.arange(first_line, first_line + count, dtype=np.int64), None
    lines = body.split("\n")
    numbers = np.arange(first_line, first_line + len(lines), dtype=np.int64)
    keep = [i for i, line in enumerate(lines)
            if (s := line.strip(" \t\r")) and not s.startswith("#")]
    lines = [lines[i] for i in keep]
    return "\n".join(lines), numbers[keep], lines


def _parse_fast(text: str, nrow: int, ncol: int) -> np.ndarray | None:
    """(nrow, ncol) values, NaN for empty cells; None when the slow path must decide."""
    data = text.encode("utf-8", errors="surrogateescape")
    if data.translate(None, _PLAIN):
        return None
    values = parse_plain(data, nrow, ncol)
    if values is not None:
        return None if np.isinf(values).any() else values
    if text[0] == "," or text[-1] == "," or _EMPTY_CELL.search(data) or \
            _EMPTY_FIRST_CELL.search(data):
        text = ("\n" + text + "\n").replace(",,", ",nan,").replace(",,", ",nan,")
        text = text.replace("\n,", "\nnan,").replace(",\n", ",nan\n")
    try:
        values = np.loadtxt(io.StringIO(text), delimiter=",", dtype=np.float64, ndmin=2,
                            comments=None)
    except ValueError:
        return None
    if values.shape != (nrow, ncol) or np.isinf(values).any():
        return None
    return values


def _cell_problem(cell: str) -> str:
    word = cell.strip().lower()
    if word in _NON_FINITE_WORDS:
        return f"non-finite value {cell.strip()!r} (write an empty cell for 'not sampled')"
    bad = _bad_byte(cell)
    if bad:
        return bad
    shown = cell if len(cell) <= 40 else cell[:37] + "..."
    return f"not a number: {shown!r}"


def _column_values(cells: list[str]):
    """One column's cells as (values, numeric): NaN where empty or not a number."""
    stripped = [cell.strip(" \t\r") for cell in cells]
    empty = np.array([not cell for cell in stripped], dtype=bool)
    joined = "\n".join(stripped)
    # numpy str arrays drop trailing NULs, so only NUL-free plain text goes through them
    if joined.isascii() and not joined.encode("ascii").translate(None, _PLAIN):
        try:  # one vectorized conversion decides for the whole column
            return (np.where(empty, "nan", np.array(stripped, dtype=np.str_)).astype(np.float64),
                    np.ones(len(cells), dtype=bool))
        except ValueError:
            pass  # e.g. '1e' or '1.2.3' somewhere: find it cell by cell
    numeric = np.array([not cell or NUMBER.fullmatch(cell) is not None for cell in stripped],
                       dtype=bool)
    filled = [cell if ok and cell else "nan" for cell, ok in zip(stripped, numeric)]
    return np.array(filled, dtype=np.str_).astype(np.float64), numeric


def _parse_slow(lines: list[str], names: list[str]):
    """Check every cell. Returns (values (R,C) NaN where empty or bad, {row: (column, reason)})."""
    ncol = len(names)
    values = np.full((len(lines), ncol), np.nan)
    problems: dict[int, tuple[str | None, str]] = {}
    for r, line in enumerate(lines):
        if _has_bad_bytes(line):
            where = _bad_byte(line)
            cell = line[:_UNDECODED.search(line).start()].count(",")
            problems[r] = (names[cell] if cell < ncol else None, where)
    split = [line.split(",") for line in lines]
    good_rows = []
    for r, cells in enumerate(split):
        if len(cells) != ncol:
            problems.setdefault(r, (names[len(cells)] if len(cells) < ncol else None,
                                    f"expected {ncol} cells (as in the header), found "
                                    f"{len(cells)}"))
        else:
            good_rows.append(r)
    for j, name in enumerate(names):
        column = [split[r][j] for r in good_rows]
        col_values, numeric = _column_values(column)
        for k in np.flatnonzero(~numeric):
            problems.setdefault(good_rows[k], (name, _cell_problem(split[good_rows[k]][j])))
        overflow = np.isinf(col_values)
        for k in np.flatnonzero(overflow):
            problems.setdefault(good_rows[k], (name, f"value {column[k].strip()!r} overflows to "
                                                     "infinity (beyond ±1.8e308)"))
        col_values[overflow] = np.nan
        values[good_rows, j] = col_values
    return values, problems


def _semantic_problems(values: np.ndarray, names: list[str], problems: dict):
    """Add row-level rule violations: empty t, partial triples, time going backwards."""
    index = {name: j for j, name in enumerate(names)}
    present = ~np.isnan(values)
    ok = np.ones(len(values), dtype=bool)
    ok[list(problems)] = False

    def flag(mask, column, reason):
        for r in np.flatnonzero(mask & ok):
            problems[int(r)] = (column, reason(int(r)))
        ok[mask] = False

    flag(~present[:, index[TIME]], TIME, lambda r: "empty time cell: every row needs t")
    for kind, triple in TRIPLES.items():
        if triple[0] not in index:
            continue
        cols = present[:, [index[n] for n in triple]]
        partial = cols.any(axis=1) & ~cols.all(axis=1)
        if partial.any():
            first_missing = np.argmin(cols, axis=1)
            for r in np.flatnonzero(partial & ok):
                have = [n for n, p in zip(triple, cols[r]) if p]
                problems[int(r)] = (triple[first_missing[r]],
                                    f"partial {kind} sample: {', '.join(have)} given but "
                                    f"{triple[first_missing[r]]} empty (all three or none)")
            ok[partial] = False
    t = values[:, index[TIME]]
    rows = np.flatnonzero(ok)
    if len(rows) > 1:
        running = np.maximum.accumulate(t[rows])
        back = np.flatnonzero(t[rows][1:] < running[:-1]) + 1
        for k in back:
            problems[int(rows[k])] = (TIME, f"time goes backwards: t={float(t[rows[k]])!r} "
                                            f"after t={float(running[k - 1])!r}")


# ----------------------------------------------------------------------------- read / write


#: Bytes of the data section parsed per slice by :func:`read` (whole lines; a longer line is
#: one slice). Bounds the parser's temporaries: its peak is the file's bytes, the result and
#: about ten times a slice, not several times the file.
SLICE_BYTES = 1 << 20


def _preamble_of(raw: bytes, where: str):
    """Parse the preamble from a prefix of ``raw`` ending at a newline (grown until the header
    is found). Returns ``(metadata, header index, names, byte offset of the data section)``."""
    size = 1 << 16
    while True:
        end = raw.rfind(b"\n", 0, size) + 1 if size < len(raw) else len(raw)
        if end == 0:   # no newline within the prefix: take up to the first one
            end = raw.find(b"\n", size) + 1 or len(raw)
        try:
            metadata, header_index, names, _ = parse_preamble(_decode(raw[:end]), where)
        except TrackError as exc:
            if end >= len(raw) or exc.line is not None:
                raise
            size = 2 * max(size, end)
            continue
        offset = 0   # the data section starts after the header's newline (same count in raw)
        for _ in range(header_index + 1):
            offset = raw.find(b"\n", offset) + 1
            if offset == 0:
                offset = len(raw)
                break
        return metadata, header_index, names, offset


def read(path: str | os.PathLike, skip_bad_rows: bool = False) -> Parsed:
    """Parse the track file at ``path``; raise :class:`TrackError` naming file, line and column.

    The data section is parsed in slices of whole lines (:data:`SLICE_BYTES`) with
    :func:`parse_rows`, as :mod:`streamcal.inputs.chunks` does, into one preallocated
    (columns, rows) float64 array whose rows become the returned columns (views, no copy).
    """
    where = os.fspath(path)
    raw = _load_bytes(where)
    metadata, header_index, names, pos = _preamble_of(raw, where)
    capacity = raw.count(b"\n", pos) + 1
    out = np.empty((len(names), capacity))
    line_numbers = np.empty(capacity, dtype=np.int64)
    n = skipped = 0
    reasons: list[str] = []
    first_line, t_before, time_col = header_index + 2, None, names.index(TIME)
    while pos < len(raw):
        end = raw.rfind(b"\n", pos, pos + SLICE_BYTES) + 1 \
            if pos + SLICE_BYTES < len(raw) else len(raw)
        if end == 0:   # one line longer than a slice
            end = raw.find(b"\n", pos + SLICE_BYTES) + 1 or len(raw)
        piece = raw[pos:end]
        body = _decode(b"\n" + piece)[1:]   # a BOM only counts at the start of the file
        values, numbers, bad, why = parse_rows(body, first_line, names, where, skip_bad_rows,
                                               t_before)
        first_line += piece.count(b"\n")
        pos = end
        out[:, n:n + len(values)] = values.T
        line_numbers[n:n + len(values)] = numbers
        n, skipped = n + len(values), skipped + bad
        reasons += why[:MAX_REASONS - len(reasons)]
        if len(values):
            t_before = max(float(np.max(values[:, time_col])),
                           -np.inf if t_before is None else t_before)
    if not n and not skipped:
        raise TrackError("no data rows after the header", where, header_index + 1)
    if not n:
        raise TrackError(f"no valid data rows: all {skipped} rows are bad; first: "
                         f"{reasons[0]}", where)
    columns = {name: out[j, :n] for j, name in enumerate(names)}
    return Parsed(columns, metadata, line_numbers[:n], skipped, reasons)


def parse_preamble(text: str, where: str):
    """Metadata, header and the text after it: ``(metadata, header index (0-based), column
    names, body text)``; raises :class:`TrackError` as :func:`read` does."""
    metadata, header_index, header, body = _split_preamble(text, where)
    version = metadata.get(VERSION_KEY)
    if version is not None and version != VERSION:
        raise TrackError(f"unsupported track format version {version!r} (this reader knows "
                         f"{VERSION})", where, None, None)
    return metadata, header_index, _parse_header(header, header_index + 1, where), body


def parse_rows(body: str, first_line: int, names: list[str], where: str, skip_bad_rows: bool,
               t_before: float | None = None):
    """Parse data lines (``body``, its first line being physical line ``first_line``).

    Returns ``(values (R,C), line numbers (R,), rows skipped, first few skip reasons)``; raises
    :class:`TrackError` at the first bad row unless ``skip_bad_rows``. ``t_before``: the largest
    time of the valid rows before ``body`` in the same file (a chunk's predecessors), so that
    time going backwards across chunks is found and worded as for the whole file.
    """
    body, numbers, lines = _body_lines(body, first_line)
    if not len(numbers):
        return np.zeros((0, len(names))), numbers, 0, []
    values = _parse_fast(body, len(numbers), len(names))
    problems: dict[int, tuple[str | None, str]] = {}
    if values is None:
        values, problems = _parse_slow(body.split("\n") if lines is None else lines, names)
    if t_before is not None:   # a valid first row carrying the earlier rows' largest time
        before = np.full((1, len(names)), np.nan)
        before[0, names.index(TIME)] = t_before
        shifted = {r + 1: v for r, v in problems.items()}
        _semantic_problems(np.vstack([before, values]), names, shifted)
        problems = {r - 1: v for r, v in shifted.items()}
    else:
        _semantic_problems(values, names, problems)
    reasons: list[str] = []
    if problems:
        bad = np.array(sorted(problems), dtype=np.int64)
        if not skip_bad_rows:
            column, reason = problems[int(bad[0])]
            raise TrackError(reason, where, int(numbers[bad[0]]), column)
        for r in bad[:MAX_REASONS]:
            column, reason = problems[int(r)]
            where_col = f" column '{column}'" if column is not None else ""
            reasons.append(f"line {int(numbers[r])}{where_col}: {reason}")
        keep = np.ones(len(values), dtype=bool)
        keep[bad] = False
        values, numbers = values[keep], numbers[keep]
    return values, numbers, len(problems), reasons


def check_metadata(metadata) -> dict[str, str]:
    """Metadata as an ordered ``{str: str}`` that survives a write/read round trip."""
    out: dict[str, str] = {}
    for key, value in dict(metadata or {}).items():
        key, value = str(key), str(value)
        if not key.strip() or key != key.strip() or ":" in key or "\n" in key or "\r" in key:
            raise TrackError(f"metadata key {key!r} cannot be written: it must be non-empty, "
                             "without ':' or line breaks or surrounding blanks")
        if "\n" in value or "\r" in value or value != value.strip():
            raise TrackError(f"metadata value of {key!r} cannot be written: it must have no "
                             "line breaks or surrounding blanks")
        out[key] = value
    return out


def _format_column(values: np.ndarray) -> list[str]:
    cells = list(map(repr, values.tolist()))
    for k in np.flatnonzero(np.isnan(values)):
        cells[k] = ""
    return cells


def format_text(columns: dict[str, np.ndarray], metadata: dict[str, str]) -> str:
    """CSV text: ``# streamcal-track: 1`` first, the other metadata in order, header, rows.

    Floats are written with ``repr`` (shortest string that reads back to the same float);
    NaN becomes an empty cell.
    """
    return format_head(list(columns), metadata) + format_rows(columns)


def format_head(names: list[str], metadata: dict[str, str]) -> str:
    """The metadata lines and the header line of :func:`format_text`, each ending in newline."""
    head = [f"# {VERSION_KEY}: {VERSION}"]
    head += [f"# {k}: {v}" for k, v in check_metadata(metadata).items() if k != VERSION_KEY]
    head.append(",".join(names))
    return "\n".join(head) + "\n"


def format_rows(columns: dict[str, np.ndarray]) -> str:
    """The data lines of :func:`format_text` (one per row, each ending in newline)."""
    cells = [_format_column(np.asarray(col, dtype=np.float64)) for col in columns.values()]
    return "\n".join(map(",".join, zip(*cells))) + "\n"


def write(path: str | os.PathLike, columns: dict[str, np.ndarray],
          metadata: dict[str, str]) -> None:
    """Write atomically; gzip-compressed when the name ends in ``.gz``."""
    data = format_text(columns, metadata).encode("utf-8")
    if Path(path).name.endswith(".gz"):
        data = gzip.compress(data, compresslevel=6, mtime=0)
    atomic_write_bytes(path, data, mode=0o644)
