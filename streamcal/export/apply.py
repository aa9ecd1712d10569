"""A calibration applied to recorded readings (docs/cli.md ``streamcal apply``).

Per magnetometer sample: the calibrated field ``f = |B| x`` (µT) with ``x = K⁻¹ (m − b − effect
terms)``, the unit direction ``x/|x|``, and, when the accelerometer is known at that instant,
the tilt-compensated magnetic heading of the body x axis. Heading: the specific force measured
at rest points up in any body frame, so with ``u = a/|a|`` the horizontal field ``n = f − (f·u) u``
points to magnetic north, ``e = n × u`` to east, and the heading is ``atan2(e_x, n_x)`` in
degrees, 0..360, clockwise from magnetic north seen from above. Under acceleration the "up"
is wrong by the acceleration's tilt; the heading is only as good as that.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..atomic import atomic_write_text
from ..calibration import Calibration


@dataclass
class Applied:
    """Results over M magnetometer samples.

    Attributes:
        t: (M,) s. field: (M,3) µT (or the calibration's unit). direction: (M,3) unit vectors.
        heading_deg: (M,) degrees from magnetic north, or None without an accelerometer.
        field_scale: |B| used; ``field_known`` False when it is K's mean radius instead.
    """

    t: np.ndarray
    field: np.ndarray
    direction: np.ndarray
    heading_deg: np.ndarray | None
    field_scale: float
    field_known: bool
    unit: str


def tilt_heading(field: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Heading (M,) degrees of body x from the field (M,3) and the specific force (M,3)."""
    up = accel / np.linalg.norm(accel, axis=1, keepdims=True)
    north = field - np.sum(field * up, axis=1, keepdims=True) * up
    east = np.cross(north, up)
    return np.degrees(np.arctan2(east[:, 0], north[:, 0])) % 360.0


def apply_calibration(cal: Calibration, t, mag, covariates: Mapping[str, np.ndarray] | None = None,
                      accel=None) -> Applied:
    """Apply ``cal`` to readings ``mag`` (M,3) at times ``t`` (M,).

    ``covariates`` ``{column: (M,)}`` feed effects beyond K and b (temp, aux channels, t);
    ``accel`` (M,3) at the same instants (NaN rows allowed) gives the heading.
    """
    mag = np.asarray(mag, dtype=float).reshape(-1, 3)
    x = cal.apply(mag, dict(covariates or {}))
    known = bool(cal.field)
    scale = float(cal.field) if known else float(np.prod(np.diag(cal.K)) ** (1 / 3))
    field = scale * x
    direction = x / np.linalg.norm(x, axis=1, keepdims=True)
    heading = None
    if accel is not None:
        accel = np.asarray(accel, dtype=float).reshape(-1, 3)
        heading = np.full(len(mag), np.nan)
        ok = np.all(np.isfinite(accel), axis=1) & (np.linalg.norm(np.nan_to_num(accel), axis=1) > 0)
        heading[ok] = tilt_heading(field[ok], accel[ok])
    return Applied(np.asarray(t, dtype=float).reshape(-1), field, direction, heading, scale,
                   known, cal.unit)


def applied_columns(applied: Applied) -> dict[str, np.ndarray]:
    """The output columns ``{name: (M,)}`` of :func:`format_csv`, in order."""
    u = applied.unit
    cols = {"t": applied.t, f"fx_{u}": applied.field[:, 0], f"fy_{u}": applied.field[:, 1],
            f"fz_{u}": applied.field[:, 2], "ux": applied.direction[:, 0],
            "uy": applied.direction[:, 1], "uz": applied.direction[:, 2]}
    if applied.heading_deg is not None:
        cols["heading_deg"] = applied.heading_deg
    return cols


def format_head(names, metadata: Mapping[str, str]) -> str:
    """``# key: value`` lines and the header line of :func:`format_csv`."""
    head = [f"# {k}: {v}" for k, v in metadata.items()]
    head.append(",".join(names))
    return "\n".join(head) + "\n"


#: Rows formatted per ``%`` in :func:`format_body`.
FORMAT_ROWS = 4096


def format_body(applied: Applied) -> str:
    """The data lines of :func:`format_csv`: one per sample, ``%.9g`` cells joined by ``,``,
    NaN → empty cell (the text ``np.savetxt(fmt="%.9g", delimiter=",")`` writes).

    Formatted with one ``%`` over the chunk, not with ``np.savetxt``: numpy's ``savetxt`` wraps
    the file in an object that holds bound methods of itself, a reference cycle that keeps the
    whole text of the chunk alive until the cyclic garbage collector runs, so memory grew by a
    chunk's text per chunk between collections (``streamcal apply`` of a 4-hour track peaked at
    1.37× a 5-minute one; ``tools/bench_replay_memory.py``).
    """
    table = np.column_stack(list(applied_columns(applied).values()))
    row = ",".join(["%.9g"] * table.shape[1]) + "\n"
    # in blocks of rows: the Python floats of one block at a time, whatever M is (a recording
    # read whole gives one piece of every sample)
    parts = [(row * len(block)) % tuple(block.ravel().tolist())
             for block in (table[k:k + FORMAT_ROWS] for k in range(0, len(table), FORMAT_ROWS))]
    return "".join(parts).replace("nan", "")


def format_csv(applied: Applied, metadata: Mapping[str, str]) -> str:
    """CSV text: ``# key: value`` lines, header, one row per sample (NaN → empty cell)."""
    return format_head(applied_columns(applied), metadata) + format_body(applied)


def write_applied(path, applied: Applied, metadata: Mapping[str, str]) -> None:
    """Write :func:`format_csv` atomically."""
    atomic_write_text(path, format_csv(applied, metadata), mode=0o644)
