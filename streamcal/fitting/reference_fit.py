"""Fits of magnetometer readings against a known expected field (the World Magnetic Model
rotated by the logged attitude, or a still vehicle at a known heading), and the mounting
rotation that matches them best.

Model, readings ``m`` (N,3) µT in the logged frame, expected body-frame field ``e`` (N,3) µT::

    R m = A e + b' + Σ_c g'_c (a_c − a0_c)

``R`` a mounting rotation (:mod:`streamcal.inputs.mount_rotations`, NONE unless detected), ``A``
symmetric (the inverse of the autopilots' symmetric soft-iron correction: scale, soft iron; 6
parameters), ``b'`` the offset and ``g'_c`` the interference per unit of channel ``c`` (a motor
current, the throttle), all in the body frame. The problem is linear: a robust (Cauchy, IRLS)
least squares with a weak Gaussian prior on every parameter — ``A`` around the identity with σ =
:data:`PRIOR_SIGMA_A`, the rest centred on the given values — so that what the slice of
attitudes does not determine stays at the prior instead of wandering (a level flight hardly
tells the vertical offset from the vertical scale). A parameter whose posterior σ stays over
:data:`HELD_SHARE` of its prior σ counts as held by the prior, and is reported.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..constants import CAUCHY_C
from ..inputs.mount_rotations import MountRotation, mount_rotations

#: Median of a χ² with 3 degrees of freedom: median ‖r‖² = this · σ² for isotropic noise σ.
CHI2_3_MEDIAN = 2.3660
#: Prior σ of the entries of A around the identity (soft iron and scale rarely exceed 30 %).
PRIOR_SIGMA_A = 0.3
#: Prior σ of offsets around the given ones, µT (hard iron of a vehicle reaches ~100 µT).
PRIOR_SIGMA_B = 200.0
#: Prior σ of an interference term, µT per channel spread (1.4826·MAD of the channel).
PRIOR_SIGMA_G = 100.0
#: A parameter whose posterior σ is over this share of its prior σ is called held (the data
#: did not halve the prior's uncertainty).
HELD_SHARE = 0.5
#: Inliers: ‖r‖² ≤ this · σ² (the 99.9 % point of a χ² with 3 degrees of freedom).
CHI2_3_INLIER = 16.27
#: A rotation other than NONE is reported only when its robust scale is below this share of
#: NONE's (a wrong mounting multiplies the misfit; a right one leaves noise and attitude error).
ROTATION_MARGIN = 0.5
#: The candidates are compared on at most this many samples, evenly spaced in the log (a wrong
#: mounting is off by tens of µT; a few thousand samples decide it).
DETECT_SAMPLES = 2000
ITERATIONS = 30
A_NAMES = ("A11", "A22", "A33", "A12", "A13", "A23")
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


@dataclass
class ReferenceFit:
    """A fit against the expected field.

    Attributes:
        rotation: the mounting rotation used (sensor → body).
        A: (3,3) symmetric; b: (3,) µT; g: ``{channel: (3,) µT per unit}``, a0 ``{channel: float}``
            — all in the body frame (``R m = A e + b + Σ g (a − a0)``).
        weights: (N,) robust weights in [0, 1]; scale: robust residual σ per axis, µT.
        rms: rms of the residual norm over the samples with weight ≥ ½, µT.
        held: ``{parameter: posterior σ / prior σ}`` for those over :data:`HELD_SHARE`.
        inliers: (N,) bool, ‖r‖² ≤ :data:`CHI2_3_INLIER` σ².
        sigma: ``{parameter: posterior σ}`` (A dimensionless, b µT, g µT per unit).
    """

    rotation: MountRotation
    A: np.ndarray
    b: np.ndarray
    g: dict = field(default_factory=dict)
    a0: dict = field(default_factory=dict)
    weights: np.ndarray | None = None
    scale: float = float("nan")
    rms: float = float("nan")
    held: dict = field(default_factory=dict)
    sigma: dict = field(default_factory=dict)
    inliers: np.ndarray | None = None

    def body_field(self, m: np.ndarray, channels: dict | None = None) -> np.ndarray:
        """Calibrated body-frame field ``A⁻¹ (R m − b − Σ g (a − a0))`` (N,3) µT."""
        r = np.asarray(m, float) @ self.rotation.matrix.T - self.b
        for name, g in self.g.items():
            r = r - np.outer(np.asarray(channels[name], float) - self.a0[name], g)
        return np.linalg.solve(self.A, r.T).T


def _design(e: np.ndarray, chans: np.ndarray) -> np.ndarray:
    """(N,3,P) Jacobian of the model's body-frame prediction w.r.t. [A (6), b (3), g (3k)]."""
    n, k = len(e), chans.shape[1]
    J = np.zeros((n, 3, 9 + 3 * k))
    for p, (i, j) in enumerate(_SYM):
        J[:, i, p] += e[:, j]
        if i != j:
            J[:, j, p] += e[:, i]
    J[:, [0, 1, 2], [6, 7, 8]] = 1.0
    for c in range(k):
        for i in range(3):
            J[:, i, 9 + 3 * c + i] = chans[:, c]
    return J


def fit_reference(m, expected, channels: dict | None = None, rotation: MountRotation | None = None,
                  b0=None, weights=None, fixed_A: np.ndarray | None = None,
                  hold=()) -> ReferenceFit:
    """Robust fit of ``R m = A e + b + Σ g (a − a0)`` (module docstring).

    Args:
        m: (N,3) readings µT; expected: (N,3) expected body-frame field µT.
        channels: ``{name: (N,)}`` interference channels (centred on their medians, a0).
        rotation: the mounting rotation (default NONE).
        b0: (3,) prior centre of the body-frame offset (default 0).
        weights: (N,) starting robust weights (default 1).
        fixed_A: hold A at this (3,3) (only offsets and channels fitted).
        hold: names of A's entries (:data:`A_NAMES`) held at the identity's value.
    """
    rotation = rotation or mount_rotations()[0]
    m = np.asarray(m, float) @ rotation.matrix.T
    e = np.asarray(expected, float)
    names = list(channels or {})
    raw = np.column_stack([np.asarray(channels[c], float) for c in names]) if names \
        else np.zeros((len(m), 0))
    a0 = np.median(raw, axis=0) if names else np.zeros(0)
    spread = np.maximum(1.4826 * np.median(np.abs(raw - a0), axis=0), 1e-9) if names else a0
    chans = raw - a0
    J = _design(e, chans)
    p = J.shape[2]
    theta0 = np.zeros(p)
    theta0[:3] = 1.0
    theta0[6:9] = np.zeros(3) if b0 is None else np.asarray(b0, float)
    prior_sigma = np.r_[np.full(6, PRIOR_SIGMA_A), np.full(3, PRIOR_SIGMA_B),
                        np.repeat(PRIOR_SIGMA_G / spread, 3)]
    free = np.ones(p, dtype=bool)
    for name in hold:
        free[A_NAMES.index(name)] = False
    if fixed_A is not None:
        fA = np.asarray(fixed_A, float)
        theta0[:6] = [fA[i, j] for i, j in _SYM]
        free[:6] = False
    target = m - np.einsum("nip,p->ni", J[:, :, ~free], theta0[~free])
    Jf = J[:, :, free]
    w = np.ones(len(m)) if weights is None else np.asarray(weights, float).copy()
    theta = theta0.copy()
    scale = np.nan
    for iteration in range(ITERATIONS):
        r = target - np.einsum("nip,p->ni", Jf, theta[free])
        r2 = np.einsum("ni,ni->n", r, r)
        scale = max(float(np.sqrt(np.median(r2) / CHI2_3_MEDIAN)), 1e-3)
        if iteration > 0:
            w = 1.0 / (1.0 + r2 / (CAUCHY_C * scale) ** 2)
        info = np.einsum("n,nip,niq->pq", w, Jf, Jf) / scale ** 2
        prior = 1.0 / prior_sigma[free] ** 2
        rhs = np.einsum("n,nip,ni->p", w, Jf, target) / scale ** 2 + prior * theta0[free]
        new = np.linalg.solve(info + np.diag(prior), rhs)
        step = np.max(np.abs(new - theta[free]))
        theta[free] = new
        if step < 1e-9:
            break
    info = np.einsum("n,nip,niq->pq", w, Jf, Jf) / scale ** 2
    prior = 1.0 / prior_sigma[free] ** 2
    cov = np.linalg.inv(info + np.diag(prior))
    labels = [*A_NAMES, "bx", "by", "bz"] + [f"{c}_{a}" for c in names for a in "xyz"]
    free_labels = [n for n, f in zip(labels, free) if f]
    share = np.sqrt(np.diag(cov)) * np.sqrt(prior)
    held_fixed = {n: 1.0 for n, f in zip(labels, free) if not f}
    A = np.zeros((3, 3))
    for k, (i, j) in enumerate(_SYM):
        A[i, j] = A[j, i] = theta[k]
    r = target - np.einsum("nip,p->ni", Jf, theta[free])
    norm = np.linalg.norm(r, axis=1)
    inl = norm ** 2 <= CHI2_3_INLIER * scale ** 2
    return ReferenceFit(
        rotation=rotation, A=A, b=theta[6:9].copy(), inliers=inl,
        g={c: theta[9 + 3 * k: 12 + 3 * k].copy() for k, c in enumerate(names)},
        a0={c: float(a0[k]) for k, c in enumerate(names)}, weights=w, scale=scale,
        rms=float(np.sqrt(np.mean(norm[inl] ** 2))) if inl.any() else float("nan"),
        held={**held_fixed,
              **{n: round(float(s), 3) for n, s in zip(free_labels, share) if s > HELD_SHARE}},
        sigma={n: float(np.sqrt(cov[k, k])) for k, n in enumerate(free_labels)})


def detect_rotation(m, expected, channels: dict | None = None,
                    candidates=None) -> tuple[ReferenceFit, list[tuple[str, float]]]:
    """The mounting rotation whose fit matches ``expected`` best (smallest robust scale; A
    held at a multiple of the identity — the gain of the readings' spread over the expected
    field's — so that no rotation can hide in it; NONE, the first candidate, unless
    the best beats it by :data:`ROTATION_MARGIN`; compared on :data:`DETECT_SAMPLES` samples),
    refitted on every sample with A free.

    Returns (that fit, ``[(name, robust scale µT)]`` of every candidate, best first).
    """
    candidates = candidates or mount_rotations()
    m, expected = np.asarray(m, float), np.asarray(expected, float)
    pick = np.unique(np.linspace(0, len(m) - 1, min(len(m), DETECT_SAMPLES)).astype(int))
    sub = {k: np.asarray(v, float)[pick] for k, v in (channels or {}).items()}
    # one gain for every candidate, from the spreads (blind to rotations and offsets): a
    # compass reading 30 % low must not make the right rotation look as bad as a wrong one
    gain = float(np.sqrt(np.trace(np.cov(m[pick].T)) / max(np.trace(np.cov(expected[pick].T)),
                                                            1e-12)))
    gain = gain if np.isfinite(gain) and gain > 0 else 1.0
    scores = []
    for rot in candidates:
        f = fit_reference(m[pick], expected[pick], sub, rotation=rot, fixed_A=gain * np.eye(3))
        scores.append((rot.name, f.scale, rot, f))
    none = scores[0]
    scores.sort(key=lambda s: s[1])
    best = scores[0] if scores[0][1] < ROTATION_MARGIN * none[1] else none
    fit = fit_reference(m, expected, channels, rotation=best[2], b0=best[3].b)
    return fit, [(name, round(float(s), 3)) for name, s, _, _ in scores]


def residual_rotation_deg(measured: np.ndarray, expected: np.ndarray,
                          weights: np.ndarray | None = None) -> float:
    """Angle (degrees) of the rotation that best turns ``measured`` (N,3) onto ``expected``
    (N,3) (weighted Wahba problem, scipy's ``align_vectors``): how far a detected mounting is
    from the exact named rotation, attitude errors included."""
    from scipy.spatial.transform import Rotation

    ok = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(expected), axis=1)
    w = None if weights is None else np.asarray(weights, float)[ok]
    rot, _ = Rotation.align_vectors(np.asarray(expected)[ok], np.asarray(measured)[ok], weights=w)
    return float(np.degrees(rot.magnitude()))
