"""What the calibration in use says about a block, without touching the calibrator's state:
the calibrated samples (:func:`apply_block`) and which samples disagree (:func:`disagreement`)."""
from __future__ import annotations

import numpy as np

from .reference import Reference, held_mask
from .staging import Stage, block_covariates


def apply_block(block, cal, coarse, shift: float, unit_vectors: bool = False) -> np.ndarray:
    """Calibrated samples of ``block`` (n,3) under the calibration ``cal`` (or, when None, the
    running sphere estimate ``coarse`` = ``(centre (3,), R)``; None: no estimate): the field in
    the sensor unit (``|B| x``), or unit directions ``x`` with ``unit_vectors``. ``shift`` (s):
    the monotone clock's shift (the clock the calibration was fitted on). NaN rows where there
    is no magnetometer sample or no estimate."""
    m = np.asarray(block.mag, dtype=float)
    out = np.full(m.shape, np.nan)
    ok = block.mag_valid
    if cal is not None:
        cov = block_covariates(block) if cal.effects else None
        if cov and shift:
            cov["t"] = cov["t"] + shift
        x = cal.apply(m[ok], {k: v[ok] for k, v in cov.items()} if cov else None)
        out[ok] = x if unit_vectors else x * (cal.field or cal.radius)
    elif coarse is not None:
        c, R = coarse
        out[ok] = (m[ok] - c) / R if unit_vectors else m[ok] - c
    return out


def disagreement(block, ref: Reference | None, stage: Stage, shift: float, cells,
                 names) -> np.ndarray:
    """Which samples of ``block`` disagree with ``ref`` (n,) bool, by the criterion that holds
    samples back (:func:`.reference.held_mask`). ``stage``: the calibrator's stage (its held
    covariates fill the block's missing ones; it is not changed), ``shift`` (s) the clock's
    shift, ``cells`` the buffer's partition, ``names`` its covariate names. All False without
    ``ref`` and on rows without a magnetometer sample or whose covariates ``ref`` lacks."""
    m = np.asarray(block.mag, dtype=float)
    out = np.zeros(len(m), dtype=bool)
    if ref is None or not len(m):
        return out
    ok = np.isfinite(m).all(axis=1)
    if not ok.any():
        return out
    if ref.cal is None:
        y = ref.project(m[ok], None, None, ())
    else:       # covariates held as the stage holds them, on the calibration's clock
        copy = Stage(1, stage.names)
        copy.held = stage.held.copy()
        m_ok, t, cov = copy.rows_of(block)
        y = ref.project(m_ok, t + shift, cov, names)
    r = np.sqrt(np.einsum("nk,nk->n", y, y))
    fin = np.isfinite(r)
    err = np.where(fin, np.abs(r - 1.0), 0.0)
    inside = err > ref.limit                # a cell only where the limit matters
    if inside.any() and ref.support is not None:
        k = np.flatnonzero(inside)
        inside[k] = ref.support[cells.cell_of(y[k] / np.maximum(r[k], 1e-300)[:, None])]
    out[ok] = held_mask(ref, err, fin, inside)
    return out
