"""The compiled LM engine: stage 2's per-sample loops in C (``_lmcore``, built with the
package), for the core model (K, b; no effect term) under the default fit's kernels (Cauchy,
Geman–McClure).

Same algebra as :mod:`streamcal.fitting.lm_blocks` (tangent-plane direction blocks, the Triggs
weights multiplied out), one pass over the samples per call instead of numpy's ~85 calls per
iteration, whose fixed cost is most of an iteration at N = 1000. The sums Σ x̄ x̄ᵀ ⊗ Q and Σ x̄ ⊗ y
come back as 72 numbers and are mapped onto the free parameters exactly as the numpy engine does.

Why not scipy.optimize.least_squares: it has no Schur elimination of the N direction blocks
(its Jacobian would be (3N, 3N + 9)), and the Triggs-corrected kernels and the paper's damping
schedule are part of the method's published behaviour (``tests/test_lm_equivalence.py``).

The extension is optional: where it was not built (no C compiler or Python headers at install), :func:`why_not`
says so and the numpy engine runs, with the same results to rounding.
"""
from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np

from .kernels import Cauchy, GemanMcClure
from .lm_blocks import _GRAM_FLAT, NumpyEngine, _core_map, _eye

try:  # built by `pip install` where a C compiler is found; numpy runs otherwise
    from ._lmcore import cost as _cost, reduce as _reduce, residuals as _residuals, step as _step
    BUILT = True
except ImportError:
    BUILT = False
try:
    from ._lmcore import SOURCE_SHA256 as _BUILT_FROM
except ImportError:
    _BUILT_FROM = ""            # built before setup.py compiled the source's hash in

NOT_BUILT = ("the compiled extension streamcal.fitting._lmcore was not built (no C compiler or "
             "Python headers at install)")
STALE = ("streamcal.fitting._lmcore was built from another version of the _lmcore.c beside it: "
         "rebuild it (pip install -e . or python setup.py build_ext --inplace)")


def _stale() -> bool:
    """Whether the _lmcore.c beside the extension (a source checkout) is not the one it was built
    from: edited since, the extension would run the old loops."""
    src = Path(__file__).with_name("_lmcore.c")
    if not BUILT or _BUILT_FROM == "unknown" or not src.is_file():   # "unknown": not by setup.py
        return False
    return hashlib.sha256(src.read_bytes()).hexdigest() != _BUILT_FROM


_WHY_NOT_BUILT = NOT_BUILT
if _stale():
    warnings.warn(f"{STALE}; the numpy engine runs until then", RuntimeWarning, stacklevel=2)
    BUILT, _WHY_NOT_BUILT = False, STALE

#: Kernel ids inside the compiled loops.
_KERNEL_IDS = {Cauchy: 0, GemanMcClure: 1}
#: Per-sample scratch between reduce and step, a row of N each: T (3,2), C (2,3), z (2,).
_WORK = 14


def available() -> bool:
    """Whether the extension was built (from the source beside it, in a checkout)."""
    return BUILT


def build_status() -> str:
    """'built', or why the compiled loops do not run (not built; built from an older source)."""
    return "built" if BUILT else _WHY_NOT_BUILT


def why_not(model, kernel) -> str:
    """Why the compiled engine does not apply ('' when it does)."""
    if model.effects:
        return "the model has effect terms"
    if type(kernel) not in _KERNEL_IDS:
        return f"kernel {getattr(kernel, 'name', kernel)!r} (only cauchy and gm are compiled)"
    if not BUILT:
        return _WHY_NOT_BUILT
    return ""


_PICKS: dict = {}


def _picks(structure: str, fit_b: bool):
    """(indices of Eᵀ G E in the 60 sums (P,P), the columns E picks (P,)) when every column of
    E picks one entry of [K b] (not for K = kI, whose column sums three), else None."""
    key = (structure, fit_b)
    if key not in _PICKS:
        E = _core_map(structure, fit_b)
        single = (E.sum(axis=0) == 1).all()
        cols = np.argmax(E, axis=0) if single else None
        _PICKS[key] = None if cols is None else (_GRAM_FLAT[np.ix_(cols, cols)], cols)
    return _PICKS[key]


class CompiledEngine:
    """:class:`~streamcal.fitting.lm_blocks.NumpyEngine`'s interface over the compiled loops."""

    solve = staticmethod(NumpyEngine.solve)

    def __init__(self, model, m_t: np.ndarray, kernel):
        self.m_t = m_t
        self.n = m_t.shape[1]
        self.kid = _KERNEL_IDS[type(kernel)]
        self.t2 = float(kernel.tau) * float(kernel.tau)
        self.E = _core_map(model.structure, model.fit_b)
        self.picks = _picks(model.structure, model.fit_b)
        self.work = np.empty((_WORK, self.n))
        self.acc = np.empty(72)
        self.eye_p = _eye(model.n_params)

    def cost(self, K, b, thetas, x):
        """(Σ ρ(‖r_j‖²), None) at directions x (3,N)."""
        return _cost(self.m_t, x, np.ascontiguousarray(K), b, self.n, self.kid, self.t2), None

    def linearize(self, K, b, thetas, x, state) -> None:
        self.K, self.b, self.x = np.ascontiguousarray(K), b, x

    def reduce(self, lam: float):
        """(S + λI (P,P), rhs (P,)) of the Schur system at damping λ."""
        _reduce(self.m_t, self.x, self.K, self.b, self.n, self.kid, self.t2, float(lam),
                self.work, self.acc)
        if self.picks is None:
            S = self.E.T @ self.acc[:60].take(_GRAM_FLAT) @ self.E
            return lam * self.eye_p + S, self.E.T @ self.acc[60:]
        gram, cols = self.picks                  # E picks columns: Eᵀ G E is a gather
        S = self.acc[:60].take(gram)
        S += lam * self.eye_p
        return S, self.acc[60:].take(cols)

    def step(self, x, dp):
        """Directions (3,N) after the global step Δp, retracted to the sphere."""
        x_new = np.empty_like(x)
        _step(x, self.n, self.work, self.E @ dp, x_new)
        return x_new

    def final(self, K, b, thetas, x, state):
        """(r (N,3), ‖r‖ (N,), ρ′(‖r‖²) (N,)) at the state, in one pass."""
        r, norm, weight = np.empty((self.n, 3)), np.empty(self.n), np.empty(self.n)
        _residuals(self.m_t, x, np.ascontiguousarray(K), b, self.n, self.kid, self.t2, r, norm,
                   weight)
        return r, norm, weight
