"""What new samples are judged against (the hold-back reference) and the hold-back criterion.

A reference is the calibration in force (samples that disagree with it are held back from the
buffer and the fits) or, before the first calibration, the running sphere estimate (which only
watches for an environment change). A sample disagrees when its relative error
``|‖y‖ − 1|`` (``y`` the sample projected by the reference) exceeds the drift limit on a
direction the reference was fitted on, or :data:`~.disturbance.GROSS` anywhere when the
reference holds samples back.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from .disturbance import GROSS
from .guard import apply_finite


@dataclass(frozen=True)
class Reference:
    """What new samples are judged against: ``y = AT``-projection of ``m − center`` (or the
    calibration ``cal`` when it has effect terms), its radius and rms (sensor unit), the drift
    ``limit`` (relative), the cells it was fitted on (``support``, None: all) and whether
    disagreeing samples are held back from the buffer (``hold``: a calibration; the running
    sphere estimate only watches, since a sphere misfits an anisotropic sensor's extremes,
    which are the samples the first fit needs most)."""

    center: np.ndarray
    AT: np.ndarray
    radius: float
    rms: float
    limit: float
    support: np.ndarray | None
    cal: Calibration | None
    hold: bool

    def project(self, m, t, cov, names) -> np.ndarray:
        """Samples ``m`` (n,3) at ``t`` (n,) s with covariates ``cov`` (n,k) named ``names``,
        projected so that ``‖y‖ = 1`` on the reference's sphere (n,3)."""
        if self.cal is None:
            return (m - self.center) @ self.AT
        return apply_finite(self.cal, m, {"t": t, **{k: cov[:, j] for j, k in enumerate(names)}})


def held_mask(ref: Reference, err, fin, inside) -> np.ndarray:
    """The hold-back criterion (n,) bool from relative errors ``err`` (n,), finite rows ``fin``
    and ``inside`` (rows on directions ``ref`` was fitted on): beyond the drift limit there,
    beyond :data:`GROSS` anywhere when ``ref`` holds samples back."""
    held = (err > ref.limit) & inside
    if ref.hold:
        held |= (err > GROSS) & fin
    return held


def beyond(y, ref: Reference, cells):
    """The hold-back criterion, pure: projections ``y`` (n,3) of samples under ``ref``.
    Returns ``held`` (n,) (relative error ``|‖y‖ − 1|`` beyond ``ref.limit`` on a direction
    ``ref`` was fitted on, or beyond :data:`GROSS` anywhere when ``ref.hold``), the errors
    (n,), ``inside`` (n,) (judged by the limit), unit directions (n,3) and their cells (n,)
    in ``cells`` (the buffer's partition: anything with ``cell_of``)."""
    r = np.sqrt(np.einsum("nk,nk->n", y, y))
    # Rows the reference cannot project (NaN: a covariate its effect terms need is missing)
    # are neither judged nor held; they go to the buffer, which projects them itself.
    fin = np.isfinite(r)
    if not fin.all():
        y = np.where(fin[:, None], y, [0.0, 0.0, 1.0])
        r = np.where(fin, r, 1.0)
    d = y / np.maximum(r, 1e-300)[:, None]
    cell = cells.cell_of(d)
    err = np.abs(r - 1.0)
    # Only directions the reference was fitted on: elsewhere it extrapolates, and a large
    # error there asks for a refit on more coverage (new cells), not for holding back.
    inside = (ref.support[cell] if ref.support is not None else True) & fin
    return held_mask(ref, err, fin, inside), err, inside, d, cell
