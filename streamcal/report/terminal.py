"""A compact terminal view of sphere coverage (like MotionCal's coverage sphere, in text).

The two hemispheres of field directions (around +Z and −Z, each seen from outside) are drawn
side by side as Lambert azimuthal equal-area discs, one character per grid point: the point is
mapped back onto the sphere and shows whether its cell of the coverage partition
(:class:`streamcal.sphere_cells.SphereCells`) holds a sample. Terminal characters are about
twice as tall as wide, so each disc is twice as many columns as rows.

    print(coverage_view(calibrator.buffer))

gives e.g. (``█`` seen, ``·`` not yet)::

     coverage 65% of the sphere (203/312 cells)
            +Y                      −Y
        ·····████            ··██████···
       ...
"""
from __future__ import annotations

import textwrap

import numpy as np

FILLED, EMPTY, GAP = "█", "·", "○"
ASCII_FILLED, ASCII_EMPTY, ASCII_GAP = "#", ".", "o"


def _disc(cells, occupied: np.ndarray, rows: int, north: bool, gap=None) -> list[str]:
    """``rows`` lines of ``2·rows + 1`` characters: 'F' seen, 'E' empty, ' ' outside, 'G' the
    grid point nearest to ``gap`` (unit (3,)) when it lies in this hemisphere."""
    cols = 2 * rows + 1
    u = (np.arange(cols) - rows) / rows * np.sqrt(2)          # Lambert X, disc radius √2
    v = (rows - 1 - 2 * np.arange(rows)) / rows * np.sqrt(2)  # Lambert Y, top row first
    U, V = np.meshgrid(u, v)
    rho2 = U * U + V * V
    inside = rho2 <= 2.0 * (1 + 0.5 / rows) ** 2
    rho2c = np.minimum(rho2, 2.0 - 1e-6)          # rim points stay in their own hemisphere
    z = 1.0 - rho2c / 2.0
    k = np.sqrt(np.clip(1.0 - z * z, 0, None)) / np.where(rho2c > 0, np.sqrt(rho2c), 1.0)
    Y = V if north else -V
    d = np.stack([U * k, Y * k, z if north else -z], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seen = np.asarray(occupied, bool)[cells.cell_of(d)].reshape(U.shape)
    grid = np.where(~inside, " ", np.where(seen, "F", "E"))
    if gap is not None and (gap[2] >= 0) == north:
        gd = d.reshape(rows, cols, 3) @ np.asarray(gap, float)
        gd = np.where(inside, gd, -np.inf)
        r, c = np.unravel_index(int(np.argmax(gd)), gd.shape)
        grid[r, c] = "G"
    return ["".join(row) for row in grid]


def coverage_map(cells, occupied, rows: int = 7, ascii: bool = False, gap=None) -> str:
    """The two hemispheres side by side, rim labelled with body axes.

    Args:
        cells: a :class:`~streamcal.sphere_cells.SphereCells` partition.
        occupied: (C,) bool, cells holding a sample.
        rows: text rows per disc (≥ 3); each disc is ``2·rows + 1`` columns.
        ascii: ``#``/``.`` instead of ``█``/``·``.
        gap: (3,) unit centre of the largest empty cap, marked ``○`` (``o``), or None.
    """
    rows = max(3, int(rows))
    glyph = {"F": ASCII_FILLED if ascii else FILLED, "E": ASCII_EMPTY if ascii else EMPTY,
             "G": ASCII_GAP if ascii else GAP, " ": " "}
    minus = "-" if ascii else "−"
    north = _disc(cells, occupied, rows, True, gap)
    south = _disc(cells, occupied, rows, False, gap)
    width = 2 * rows + 1
    sep = " " * 8

    def centred(text):
        return text.center(width + 6)

    lines = [centred("+Y") + sep + centred(minus + "Y")]
    mid = rows // 2
    for i, (a, b) in enumerate(zip(north, south)):
        a = "".join(glyph[ch] for ch in a)
        b = "".join(glyph[ch] for ch in b)
        left, right = (minus + "X ", " +X") if i == mid else ("   ", "   ")
        lines.append(f"{left}{a}{right}{sep}{left}{b}{right}")
    lines.append(centred(minus + "Y") + sep + centred("+Y"))
    lines.append(centred("top (+Z)") + sep + centred(f"underside ({minus}Z)"))
    return "\n".join(line.rstrip() for line in lines)


def coverage_view(buffer, report=None, rows: int = 7, ascii: bool = False,
                  width: int = 96, occupied=None) -> str:
    """Coverage percentage, the two-hemisphere map and the hint, for a
    :class:`~streamcal.stream.coverage.CoverageBuffer` (``report``: its
    :meth:`~streamcal.stream.coverage.CoverageBuffer.report`, computed when None; ``occupied``
    (n_cells,) bool: the cells to draw, the buffer's current ones when None — pass the report's
    when it was taken earlier, so that map and figures agree); the hint is wrapped to ``width``
    columns."""
    report = report if report is not None else buffer.report()
    if not report.measured:     # no map: the frame places no direction yet
        return "\n".join([f"coverage not measured ({report.n_samples} samples stored)",
                          textwrap.fill(f"hint: {report.hint}", width=width,
                                        subsequent_indent="      ")])
    occupied = buffer.occupied if occupied is None else occupied
    gap = report.empty_cap_center if report.empty_cap_deg >= 20.0 else None
    head = (f"coverage {100 * report.fraction:.0f}% of the sphere "
            f"({int(occupied.sum())}/{buffer.cells.n_cells} cells, {report.n_samples} samples)")
    legend = ("#" if ascii else FILLED) + " seen  " + ("." if ascii else EMPTY) + " not yet"
    if gap is not None:
        legend += "  " + ("o" if ascii else GAP) + f" centre of the largest gap ({report.empty_cap_deg:.0f}°)"
    hint = textwrap.fill(f"hint: {report.hint}", width=width, subsequent_indent="      ")
    return "\n".join([head, coverage_map(buffer.cells, occupied, rows, ascii, gap), legend, hint])
