"""The attitude reference as a second block of rows of the held fit (issue #24).

The held fit (:func:`streamcal.diagnosis.held.fit.held_fit`) sees only the field's magnitude,
which a rotation of the field's direction leaves unchanged: on a level flight it can trade the
vertical scale for the vertical offset and turn the heading. Where the log has an attitude and
a place, the direction each sample should have is known up to the attitude's error: the World
Magnetic Model field at the place, rotated into the body frame by the logged attitude
(:mod:`streamcal.fitting.attitude_reference`), is the unit vector û_j, and in the frame of the
calibration (``body = F x``: F = Qᵀ for a calibration carrying ``frame_rotation_Q``, PX4's
rotation for ``sensor_mag`` readings, else the identity) the model direction x_j = Fᵀ û_j.

Frame. An autopilot corrects with a symmetric matrix and a mounting rotation (ArduPilot's
COMPASS_DIA/ODI and COMPASS_ORIENT, PX4's CAL_MAGn_*SCALE/*OFF and _ROT): the linear map from
body direction to reading is A = S V, S symmetric, V the rotation it holds. A small turn of the
field, which the reference sees, has no place in those parameters, so the refinement keeps V
(that of the calibration held: A₀ = K₀ F₀ᵀ = S₀ V, S₀ = (K₀K₀ᵀ)^½) and lets S follow K:
S(K) = (K Kᵀ)^½ and the calibration's frame Q(K) = K⁻¹ S(K) V (x = Q û), which
:func:`frame` gives and the refined calibration carries as ``frame_rotation_Q``. Then the
calibration a firmware loads (:mod:`streamcal.export`, the polar form of K⁻¹) points as the
refinement does.

The block's residual is the part of ``m_j − g(x_j)`` (sensor unit, g the model surface) in
the plane normal to the surface at x_j: two components d_j (the field's size is the magnitude
block's). Its rows are ``t_kᵀ ∂g/∂p`` for the two unit tangents t_k, the magnitude block's
``nᵀ ∂g/∂p`` with n replaced by t_k (:func:`streamcal.diagnosis.held.fit.jacobian`).

The dependence of x on K enters the rows of the K entries through ∂g/∂x · ∂Q/∂K û (∂Q/∂K by
central differences of the 3×3 :func:`frame`).

Its width is the reference's own: the robust per-axis scale σ_a (radians) of the tangential
residual of the robust fit against the reference (:func:`streamcal.fitting.attitude_reference.
reference_inliers`: the attitude's error, the model's, the noise), times the field radius r,
as the magnitude block's is the noise floor: each block's samples count as independent at their
own width. The samples are the ones every heading figure is over (the reference fit's inliers,
over the interference channels of the calibration held), so the heading a refinement is judged
by is over the samples it was fitted on.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...calibration import Calibration
from ...constants import ATTITUDE_COLUMNS, CAUCHY_C
from ...fitting.attitude_reference import CAVEAT, MIN_SAMPLES, attitude_data, reference_inliers
from ...fitting.entries import K_INDEX
from ...inputs.autopilot_cal import px4_rotation
from .fit import jacobian, project

#: A held calibration whose median direction is further than this from the reference (degrees)
#: is not refined against it: a compass mounted otherwise than the calibration says, or a yaw
#: that does not come from this compass.
MAX_MEDIAN_DEG = 30.0
#: Median of a χ² with 2 degrees of freedom: median ‖d‖² = this · σ² for isotropic noise σ.
CHI2_2_MEDIAN = 2.0 * np.log(2.0)


@dataclass(frozen=True)
class ReferenceRows:
    """The reference samples of a recording, for a held fit.

    Attributes:
        index: (M,) indices of the samples among the recording's magnetometer samples.
        body: (M,3) unit body-frame direction the reference expects.
        V: (3,3) the rotation the calibration holds (module doc).
        width_rad: robust per-axis width of the direction residual (radians).
        place: the World Magnetic Model figures used (:func:`streamcal.geomag.wmm_field`).
        radius: field radius (sensor unit) the widths are scaled by; set by :meth:`scaled`.
    """

    index: np.ndarray
    body: np.ndarray
    V: np.ndarray
    width_rad: float
    place: dict
    radius: float = float("nan")

    @property
    def sigma(self) -> float:
        """Robust width of one component of d (sensor unit)."""
        return self.width_rad * self.radius

    def scaled(self, radius: float) -> "ReferenceRows":
        return replace(self, radius=float(radius))

    def at(self, rows) -> "ReferenceRows":
        """The reference samples among the sample indices ``rows`` (sorted), indexed into them."""
        rows = np.asarray(rows)
        pos = np.searchsorted(rows, self.index)
        ok = pos < len(rows)
        ok[ok] = rows[pos[ok]] == self.index[ok]
        return replace(self, index=pos[ok], body=self.body[ok])

    def information_rows(self, names, K, b, terms, m, cov, sigma: float) -> np.ndarray:
        """:func:`information_rows` of this reference."""
        return information_rows(self, names, K, b, terms, m, cov, sigma)

    def joint_block(self, m, cov, tau: float, n_held: int, K_base=None) -> "JointBlock":
        """This reference's :class:`JointBlock` in a held fit of ``m`` (magnitude width
        ``tau``, ``n_held`` held effect terms first, ``K_base`` the K its radius scales)."""
        return JointBlock(self, m, cov, tau, n_held, K_base)

    def describe(self) -> dict:
        """What a calibration file and ``diagnose --json`` say of the reference used."""
        return {"samples": int(len(self.index)),
                "width_deg": round(float(np.degrees(self.width_rad)), 3),
                "place": {k: self.place.get(k) for k in ("source", "lat", "lon", "alt_km",
                                                          "date")},
                "caveat": CAVEAT}


def _frame(cal: Calibration | None, meta) -> np.ndarray:
    """F (3,3) with body = F x, x the calibration's direction (as
    :func:`streamcal.fitting.attitude_reference.body_field` turns it)."""
    Q = (cal.extra or {}).get("frame_rotation_Q") if cal is not None else None
    if Q is not None:
        return np.asarray(Q, float).T
    R = px4_rotation(meta or {})
    return np.eye(3) if R is None else np.asarray(R, float)


def reference_rows(track, calibration: Calibration | None,
                   location: dict | None = None) -> tuple[ReferenceRows | None, str]:
    """``(rows, "")`` when ``track`` has an attitude and a place (``location``, else its GPS)
    and the held ``calibration`` (None: the readings' own frame) points within
    :data:`MAX_MEDIAN_DEG` of the reference; else ``(None, why not)``."""
    if not all(track.has(c) for c in ATTITUDE_COLUMNS):
        return None, "the log has no attitude"
    data, why = attitude_data(track, location)
    if data is None:
        return None, why
    aux = dict((calibration.effects if calibration else {}).get("aux_interference") or {})
    kept, fit = reference_inliers(data, list(aux.get("channels", {})))
    if len(kept.t) < MIN_SAMPLES:
        return None, f"only {len(kept.t)} samples follow the attitude reference"
    e = kept.expected / np.linalg.norm(kept.expected, axis=1, keepdims=True)
    f = fit.body_field(data.m, data.cov)[fit.inliers]
    d = f - e * np.linalg.norm(kept.expected, axis=1, keepdims=True)
    d -= np.sum(d * e, axis=1, keepdims=True) * e                      # tangential, µT
    field = float(np.median(np.linalg.norm(kept.expected, axis=1)))
    width = float(np.sqrt(np.median(np.sum(d * d, axis=1)) / CHI2_2_MEDIAN)) / field
    F = _frame(calibration, track.metadata)
    if calibration is not None:
        held = calibration.apply(kept.m, kept.cov) @ F.T
        cosang = np.sum(held * e, axis=1) / np.linalg.norm(held, axis=1)
        median = float(np.degrees(np.arccos(np.clip(np.median(cosang), -1, 1))))
        if median > MAX_MEDIAN_DEG:
            return None, (f"the calibration held points {median:.0f}° (median) from the attitude "
                          f"reference: a mounting or a yaw it does not describe")
    K0 = np.asarray(calibration.K, float) if calibration is not None else np.eye(3)
    V = np.linalg.solve(_sqrt_gram(K0), K0 @ F.T)
    return ReferenceRows(index=np.asarray(kept.rows), body=e, V=V, width_rad=max(width, 1e-6),
                         place=dict(kept.ref)), ""


def _sqrt_gram(K: np.ndarray) -> np.ndarray:
    """(K Kᵀ)^½, symmetric positive definite."""
    w, U = np.linalg.eigh(K @ K.T)
    return (U * np.sqrt(np.maximum(w, 0.0))) @ U.T


def frame(K, V: np.ndarray) -> np.ndarray:
    """Q(K) = K⁻¹ (K Kᵀ)^½ V (3,3), orthogonal: the frame of a calibration with core K whose
    body-to-reading map is symmetric after the rotation V (module doc); x = Q û."""
    K = np.asarray(K, float)
    return np.linalg.solve(K, _sqrt_gram(K) @ V)


#: Step of the central differences of :func:`frame`, relative to the field radius.
FRAME_STEP = 1e-6


def _frame_derivatives(K, V, names) -> dict:
    """{K entry name: ∂Q/∂K_entry (3,3)} for the K entries among ``names``."""
    K = np.asarray(K, float)
    h = FRAME_STEP * float(np.prod(np.abs(np.diag(K))) ** (1 / 3))
    out = {}
    for name in names:
        if name in K_INDEX:
            E = np.zeros((3, 3))
            E[K_INDEX[name]] = h
            out[name] = (frame(K + E, V) - frame(K - E, V)) / (2 * h)
    return out


def _tangents(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (M,3) each spanning with ``normal`` (M,3) an orthonormal basis."""
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normal, t1)


def _at(ref: ReferenceRows, m, cov):
    return np.asarray(m)[ref.index], {k: np.asarray(v)[ref.index] for k, v in cov.items()}


def residual(ref: ReferenceRows, K, b, terms, m, cov):
    """d (M,2) sensor unit, with what its rows need: (d, x, (t1, t2), D, cov at the samples)."""
    mr, cr = _at(ref, m, cov)
    r, x, _, normal, D = project(K, b, terms, mr, cr, ref.body @ frame(K, ref.V).T, iters=0)
    t1, t2 = _tangents(normal)
    d = -np.column_stack([np.sum(t1 * r, axis=1), np.sum(t2 * r, axis=1)])
    return d, x, (t1, t2), D, cr


def _rows(ref: ReferenceRows, free, new_terms, K, x, tangents, D, cr,
          K_base=None) -> list[np.ndarray]:
    """The rows (M,P) of each tangent: ``t_kᵀ ∂g/∂p`` at the fixed x
    (:func:`streamcal.diagnosis.held.fit.jacobian`; ``K_base`` the K the radius scales,
    default K), plus for the K entries the turn of x with K (∂g/∂x ∂Q/∂K û, ∂g/∂x = D K; the
    radius does not turn it: Q(cK) = Q(K))."""
    K = np.asarray(K, float)
    K_base = K if K_base is None else K_base
    u = x @ K.T
    turns = _frame_derivatives(K, ref.V, free)
    out = []
    for t in tangents:
        A = jacobian(list(free), new_terms, x, t, D, cr, u, K_base)
        tDK = np.einsum("ni,nij->nj", t, D) @ K            # tᵀ ∂g/∂x (M,3)
        for name, dQ in turns.items():
            A[:, list(free).index(name)] += np.einsum("nj,nj->n", tDK, ref.body @ dQ.T)
        out.append(A)
    return out


def information_rows(ref: ReferenceRows, names, K, b, terms, m, cov, sigma: float) -> np.ndarray:
    """(2M, P) rows of the core parameters ``names`` at K, b (``terms`` held), scaled so that
    stacked under the magnitude rows of noise ``sigma`` their AᵀA/σ² is the block's
    information (the Cramér–Rao choice of :func:`streamcal.diagnosis.held.fit.choose_free`)."""
    _, x, tangents, D, cr = residual(ref, K, b, terms, m, cov)
    A = np.vstack(_rows(ref, names, [], K, x, tangents, D, cr))
    return A * (sigma / ref.sigma)


class JointBlock:
    """The block's share of the held fit's robust cost Σ log(1 + ‖d‖²/τ_r²) (τ_r the Cauchy
    width of :attr:`ReferenceRows.sigma`) and of its normal equations. The magnitude block's H
    and gradient (Σ w a aᵀ, −Σ w s a) leave its 1/τ² out, so this block's carry (τ/τ_r)²,
    ``tau`` the magnitude block's width: each block weighted by its own width."""

    def __init__(self, ref: ReferenceRows, m, cov, tau: float, n_held: int, K_base=None):
        self.ref, self.m, self.cov, self.n_held, self.K_base = ref, m, cov, n_held, K_base
        self.tau_ref = CAUCHY_C * ref.sigma
        self.scale = (tau / self.tau_ref) ** 2

    def cost(self, K, b, terms) -> float:
        d = residual(self.ref, K, b, terms, self.m, self.cov)[0]
        return float(np.sum(np.log1p(np.sum(d * d, axis=1) / self.tau_ref ** 2)))

    def _rows(self, free, K, b, terms):
        """d (M,2), the robust weights (M,) and the rows (M,P) of each tangent."""
        d, x, tangents, D, cr = residual(self.ref, K, b, terms, self.m, self.cov)
        w = 1.0 / (1.0 + np.sum(d * d, axis=1) / self.tau_ref ** 2)
        return d, w, _rows(self.ref, free, terms[self.n_held:], K, x, tangents, D, cr,
                           self.K_base)

    def linearize(self, free, K, b, terms) -> tuple[float, np.ndarray, np.ndarray]:
        """(cost, H (P,P), gradient (P,)) of the block at K, b, ``terms`` (held ones first)."""
        d, w, rows = self._rows(free, K, b, terms)
        H = sum(np.einsum("np,nq->pq", A * w[:, None], A) for A in rows)
        grad = -sum(np.einsum("np,n->p", A, w * d[:, k]) for k, A in enumerate(rows))
        cost = float(np.sum(np.log1p(np.sum(d * d, axis=1) / self.tau_ref ** 2)))
        return cost, self.scale * H, self.scale * grad

    def information(self, free, K, b, terms) -> np.ndarray:
        """(P,P) Σ w AᵀA / σ̂² of the block at K, b, ``terms``, σ̂ the robust scale of d there:
        its share of the fit's covariance, as the magnitude block's takes its own σ̂."""
        d, w, rows = self._rows(free, K, b, terms)
        width = float(np.sqrt(np.median(np.sum(d * d, axis=1)) / CHI2_2_MEDIAN))
        H = sum(np.einsum("np,nq->pq", A * w[:, None], A) for A in rows)
        return H / max(width, 1e-12) ** 2
