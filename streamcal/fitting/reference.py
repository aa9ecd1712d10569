"""The reference calibration methods the autocalibration paper compares against (its Table I).

Each method is a pure function of normalized samples ``m_n`` (N,3) (paper §II-B: median
centred, divided by the standard deviation) returning a sensor model ``(A, b)`` in normalized
units with ``m_n ≈ A x + b``, ``x`` unit vectors. ``A`` is general; the dispatcher
(:func:`streamcal.fitting.fit`) denormalizes and puts it in canonical form (RQ, paper §II-A).
Iterative methods stop at ``max_iter`` iterations or when the objective changes by less than
``rtol`` relative to its previous value (paper §III-A: 300 and 1e-6).

========================  =========================================  ==============================
name                      module                                     paper
========================  =========================================  ==============================
``magical``               :mod:`streamcal.fitting.magical`               Papafotis & Sotiriadis 2019
``dorveaux``              :mod:`streamcal.fitting.dorveaux`              Dorveaux et al. 2009
``vasconcelos``           :mod:`streamcal.fitting.vasconcelos`           Vasconcelos et al. 2011
``kok_schon``             :mod:`streamcal.fitting.kok_schon`             Kok & Schön 2016
========================  =========================================  ==============================
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError, InsufficientDataError

def check_samples(m_n, method: str, minimum: int) -> np.ndarray:
    """``m_n`` as a float (N,3) array with finite values and at least ``minimum`` rows;
    :class:`InputError` / :class:`InsufficientDataError` naming the method otherwise."""
    m = np.asarray(m_n, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise InputError(f"{method}: expected samples of shape (N, 3), found {m.shape}")
    if not np.all(np.isfinite(m)):
        rows = np.flatnonzero(~np.isfinite(m).all(axis=1))
        raise InputError(f"{method}: sample row {rows[0]} has a non-finite value "
                         f"({rows.size} such rows); drop them before fitting")
    if m.shape[0] < minimum:
        raise InsufficientDataError(f"{method}: needs at least {minimum} samples, "
                                    f"found {m.shape[0]}")
    return m


def converged(f_prev: float, f: float, rtol: float) -> bool:
    """Relative function tolerance test ``|f_prev − f| ≤ rtol · f_prev`` (also true when the
    objective reached exactly zero)."""
    return abs(f_prev - f) <= rtol * abs(f_prev) or f == 0.0
