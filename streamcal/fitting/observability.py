"""When the data cannot decide, say so (issue 2, item 8).

With unit directions x_j free, a sample tells the model only along the ellipsoid's normal at
K x_j + b, n_j ∝ K⁻ᵀx_j; eliminating the directions leaves the reduced Fisher information

    S = (1/N) Σ a_j a_jᵀ,   a_j = n_jᵀ ∂(K x_j + b)/∂p.

Directions on a great circle or in one small cap leave combinations of p with no information
(for a plane, a whole family of ellipsoids passes through the data, so S is singular at any of
them — which is why S must be taken at the fitted K, not at the directions alone). We compare S
with its value for directions spread uniformly over the sphere, at the same K (generalized
eigenvalues): ``information`` is the smallest ratio, 1 for a full sphere, 0 for a plane.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dsygv, dtrtri

from ..calibration import field_radius
from .lm import K_ENTRIES

#: Below this relative information the fit is refused. Calibrated so that a 75° cap (0.0015) or a
#: ±20° band (0.007; about a third of the sphere) passes and a 60° cap (0.0002) or a ±10° band
#: (0.0004) does not
#: (tests/test_fit_core.py).
MIN_INFORMATION = 1e-3
AXES = ("x", "y", "z")


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n,3) nearly uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5 ** 0.5) * i
    rho = np.sqrt(1 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def inverse3(K: np.ndarray) -> np.ndarray:
    """K⁻¹ of a 3×3 matrix; an upper-triangular K (the canonical sensor matrix) by LAPACK's
    triangular inverse (dtrtri, ~2 µs against ~12 µs for np.linalg.inv's wrapper). Raises
    LinAlgError when K is singular, like np.linalg.inv."""
    K = np.asarray(K, dtype=float)
    if K[1, 0] == 0.0 and K[2, 0] == 0.0 and K[2, 1] == 0.0:
        inv, info = dtrtri(K, lower=0)
        if info == 0:
            return inv
    return np.linalg.inv(K)


def _rows_t(x: np.ndarray, K: np.ndarray, structure: str, fit_b: bool) -> np.ndarray:
    """The rows a_j as columns, (p, N): samples along the fast axis, so that every step below
    is a contiguous pass (half the cost of the (N, p) layout at N = 1000)."""
    # n_j ∝ K⁻ᵀx_j (one 3×3 inverse instead of a solve per call: a batched solve costs ~10x
    # the product at N = 2000)
    xt = x.T
    nt = inverse3(K).T @ xt
    nt /= np.sqrt(np.einsum("ij,ij->j", nt, nt))
    if structure == "sphere":
        k = np.einsum("ij,ij->j", nt, xt)[None, :]
        return np.concatenate([k, nt]) if fit_b else k
    rows, cols = _ENTRY_INDEX[structure]
    at = np.empty((len(rows) + 3 * fit_b, x.shape[0]))
    np.multiply(nt[rows], xt[cols], out=at[:len(rows)])
    if fit_b:
        at[len(rows):] = nt
    return at


#: Uniform directions of the reference information. Against 2000, 300 Fibonacci directions
#: change the relative information by at most 0.054 % (6 models K × full/diag/sphere × with and
#: without b × 29 direction sets: caps 30–120°, bands ±5–45°, a plane, a sphere, freeimucal), far
#: inside the margins of the decisions (75° cap 0.0015, 60° cap 0.0002 vs MIN_INFORMATION).
UNIFORM_COUNT = 300
_UNIFORM_DIRECTIONS = None
#: (rows, columns) of the free entries of K per structure, for :func:`_rows_t`.
_ENTRY_INDEX = {name: (np.array([i for i, _ in e]), np.array([j for _, j in e]))
                for name, e in K_ENTRIES.items()}
_CELL_CENTRES: dict = {}


def coverage_fraction(x: np.ndarray, n_cells: int = 100) -> float:
    """Fraction of ``n_cells`` equal-area cells (nearest Fibonacci centre) holding a direction."""
    x = np.asarray(x, dtype=float)
    if len(x) == 0:
        return 0.0
    centres = _CELL_CENTRES.get(n_cells)
    if centres is None:
        centres = _CELL_CENTRES[n_cells] = fibonacci_sphere(n_cells)
    hit = np.zeros(n_cells, dtype=bool)
    for start in range(0, len(x), 8192):  # bounded (8192, n_cells) temporaries
        hit[np.argmax(x[start:start + 8192] @ centres.T, axis=1)] = True
    return float(hit.sum() / n_cells)


def _axis_name(v: np.ndarray) -> str:
    i = int(np.argmax(np.abs(v)))
    return ("+" if v[i] > 0 else "-") + AXES[i]


@dataclass(frozen=True)
class Observability:
    information: float      # smallest generalized eigenvalue of S vs uniform, 0..1
    coverage: float         # fraction of 100 equal-area cells hit
    ok: bool
    message: str


def assess(x: np.ndarray, structure: str = "full", fit_b: bool = True, K: np.ndarray | None = None,
           m: np.ndarray | None = None, min_information: float = MIN_INFORMATION) -> Observability:
    """Judge whether directions x (N,3), seen through the fitted K (3,3; default I), determine
    the model; say what is missing if not (``m``, the (N,3) measurements, lets the message name
    the plane of a planar recording in body axes even when the fitted model is meaningless)."""
    global _UNIFORM_DIRECTIONS
    x = np.asarray(x, dtype=float)
    K = np.eye(3) if K is None else np.asarray(K, dtype=float)
    K = K / field_radius(K)  # the ratio below is scale-free
    if _UNIFORM_DIRECTIONS is None:
        _UNIFORM_DIRECTIONS = fibonacci_sphere(UNIFORM_COUNT)
    # the samples' rows and the uniform directions' rows in one pass, then each Gram matrix
    n = len(x)
    at = _rows_t(np.concatenate([x, _UNIFORM_DIRECTIONS]), K, structure, fit_b)
    S = at[:, :n] @ at[:, :n].T / max(n, 1)
    U = at[:, n:] @ at[:, n:].T / UNIFORM_COUNT
    # the generalized eigenvalues of (S, U) by LAPACK's dsygv (Cholesky of U, then the
    # symmetric problem): one call instead of numpy's four
    w, _, status = dsygv(S, U, jobz="N")
    if status:
        raise np.linalg.LinAlgError(
            f"the reference information is singular (dsygv info {status})" if status > len(S)
            else f"the information's eigenvalues did not converge (dsygv info {status}; "
                 f"finite directions: {bool(np.isfinite(x).all())})")
    info = float(max(w[0], 0.0))
    cover = coverage_fraction(x)
    if info >= min_information:
        return Observability(info, cover, True, "")
    return Observability(info, cover, False, _what_is_missing(x, info, cover, m))


def _what_is_missing(x: np.ndarray, info: float, cover: float, m: np.ndarray | None) -> str:
    if m is not None:
        centred = m - np.median(m, axis=0)
        w, V = np.linalg.eigh(centred.T @ centred / len(m))
        w = w / max(w[-1], 1e-300)
    else:
        w, V = np.linalg.eigh(x.T @ x / len(x))
    mean = x.mean(axis=0)
    head = (f"the directions seen cover {cover:.0%} of the sphere and leave the model "
            f"undetermined (relative information {info:.3f} < {MIN_INFORMATION})")
    if w[0] < 0.03:
        normal = _axis_name(V[:, 0])
        return (f"{head}: they lie on a great circle, never leaving the plane perpendicular to "
                f"{normal}, so the scale along {normal[1]} and its cross terms are unknown. "
                f"Tilt the board so that {normal[1]} points towards and away from the field "
                f"(rotate it about the other two axes), then record again.")
    if np.linalg.norm(mean) > 0.5:
        seen = _axis_name(mean)
        opposite = ("-" if seen[0] == "+" else "+") + seen[1]
        return (f"{head}: they stay on one side, around {seen}. Turn the board over so the field "
                f"also arrives from {opposite}, then record again.")
    return f"{head}. Rotate the board through more orientations (all faces up in turn)."
