"""Re-estimate only what a recording determines, holding the rest (issue #10).

A slice of the sphere (a drone flying level, a robot driving) constrains some combinations of
K and b well and leaves others free. Here the parameters are named one by one
(``K_xx, K_xy, K_xz, K_yy, K_yz, K_zz`` — the upper-triangular K — and ``b_x, b_y, b_z``, sensor
unit) and each is either *estimated* from the recording or *held* at a given value; the field
radius ``radius`` (the scale of the whole K, the field strength) is one more where the diagonal
of K is not all estimated (:func:`radius_free`).

Which are estimated is decided by the Cramér–Rao bound. With directions free, sample j tells the
model only along the surface normal n_j, through the row a_j = n_jᵀ ∂g(x_j)/∂p
(:mod:`streamcal.fitting.observability`); with per-axis noise σ the information is
F = Σ a_j a_jᵀ / σ², and the predicted standard error of the estimated set E is
sqrt(diag (F_EE)⁻¹). :func:`choose_free` starts from every parameter of the model and holds the
one with the largest predicted error until every remaining one is below the tolerance
(:data:`TOLERANCE` × the field radius r, the geometric mean of diag K). This weighs the number
of samples and the noise, not a scale-free coverage fraction: a long quiet slice determines more
than a short noisy one of the same directions.

:func:`held_fit` is a robust Gauss–Newton/LM on the scalar normal residual
s_j = −n_jᵀ(g(x̂_j) − m_j) (x̂_j the closest point of the model surface, re-projected every
iteration), Cauchy weights of width 2.385 σ̂, over the estimated core parameters and the
parameters of any added effect term; the covariance of the estimate is σ̂² (AᵀWA)⁻¹. With an
attitude reference (:mod:`.reference_rows`) its direction residual is a second robust block.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Mapping, Sequence

import numpy as np

from ...constants import CAUCHY_C, OUTLIER_WIDTHS
from ...errors import InsufficientDataError
from ...fitting.damped_lm import CONVERGED, Damping, damped_lm
from ...fitting.entries import (B_INDEX, B_PARAMS, K_INDEX, K_PARAMS, RADIUS, entry,
                                field_radius, shifted)
from ..residuals import GN_ITERATIONS, closest_point

#: A parameter is re-estimated when its predicted (Cramér–Rao) standard error is below this
#: fraction of the field radius r (0.5 % of r: 0.24 µT at 48 µT).
TOLERANCE = 0.005
MAX_ITER, RTOL = 30, 1e-7
#: λ ÷10 after an accepted step, ×10 after a rejected one.
DAMPING = Damping(start=1e-3, down=10.0, up=10.0, floor=1e-12)


def core_params(model: Sequence[str]) -> list[str]:
    """The named core parameters a model has (hard_iron → b; soft_iron → 6 K entries; scale →
    the diagonal). A model without soft_iron/scale keeps K as given (held)."""
    names = []
    if "soft_iron" in model:
        names += [n for n, _ in K_PARAMS]
    elif "scale" in model:
        names += ["K_xx", "K_yy", "K_zz"]
    if "hard_iron" in model:
        names += [n for n, _ in B_PARAMS]
    return names


def project(K, b, terms, m, cov, x=None, iters: int = GN_ITERATIONS):
    """Closest point of the model surface to each reading (eq. 41): returns ``r`` (N,3) =
    g(x̂) − m, ``x̂`` (N,3), the signed normal distance ``s`` (N,), the unit normals (N,3) and
    the model Jacobian D = ∂g/∂u (N,3,3). ``terms``: [(effect term, θ)] in sensor units."""
    cal = SimpleNamespace(K=np.asarray(K, float), b=np.asarray(b, float))
    if x is None:
        x = np.linalg.solve(cal.K, (m - cal.b).T).T
    r, x, s, normal, J = closest_point(cal, terms, m, cov, x, iters)
    # one product when J is the same for every sample, then a (read-only) broadcast view
    return r, x, s, normal, np.broadcast_to(J @ np.linalg.inv(cal.K), (len(x), 3, 3))


def jacobian(free: Sequence[str], terms, x, normal, D, cov, u, K_base=None) -> np.ndarray:
    """Rows a_j = n_jᵀ ∂g(x_j)/∂p (N,P) for the named core parameters ``free`` then every θ of
    ``terms`` (the derivative of s_j is −a_j); ``u`` = K x (N,3). ``K_base``: the K the
    ``radius`` scales (:func:`streamcal.fitting.entries.shifted`), needed with ``radius``."""
    nD = np.einsum("ni,nik->nk", normal, D)            # nᵀ ∂g/∂u
    cols = []
    for name in free:
        if name == RADIUS:      # ∂K/∂r = K_base / r(K_base)
            K_base = np.asarray(K_base, float)
            cols.append(np.einsum("nk,nk->n", nD, x @ K_base.T) / field_radius(K_base))
        elif name in K_INDEX:
            i, j = K_INDEX[name]
            cols.append(nD[:, i] * x[:, j])
        else:
            cols.append(normal[:, B_INDEX[name]])
    for term, theta in terms:
        cols.extend(np.einsum("ni,nip->np", normal, term.jac_theta(theta, u, cov)).T)
    return np.column_stack(cols) if cols else np.zeros((len(x), 0))


def predicted_errors(A: np.ndarray, sigma: float) -> np.ndarray:
    """Cramér–Rao standard errors sqrt(diag (AᵀA/σ²)⁻¹) (inf where undetermined)."""
    if A.shape[1] == 0:
        return np.zeros(0)
    F = np.einsum("np,nq->pq", A, A) / sigma ** 2
    w, V = np.linalg.eigh(F)
    if w[-1] <= 0:
        return np.full(A.shape[1], np.inf)
    with np.errstate(divide="ignore"):
        inv = np.where(w > w[-1] * 1e-12, 1.0 / w, np.inf)
    var = (V ** 2) @ np.where(np.isfinite(inv), inv, 1e300)
    return np.sqrt(np.minimum(var, np.inf))


def choose_free(names: Sequence[str], K, b, m, cov, terms, sigma: float,
                tolerance: float, keep: Sequence[str] = (),
                reference=None) -> tuple[list[str], dict]:
    """Estimated subset of ``names`` (see module doc) and every parameter's predicted error
    when it was last considered ({name: σ_CR}, sensor unit). Parameters in ``keep`` are never
    held: the worst of the others is held until every estimated one is within ``tolerance``
    or only ``keep`` is left (whose errors are then the caller's to judge). ``reference``
    (:class:`~.reference_rows.ReferenceRows`): its information counts too."""
    _, x, _, normal, D = project(K, b, terms, m, cov)
    A = jacobian(list(names), [], x, normal, D, cov, x @ np.asarray(K).T, K)
    if reference is not None:
        A = np.vstack([A, reference.information_rows(names, K, b, terms, m, cov, sigma)])
    free = list(names)
    errors = {}
    while free:
        idx = [list(names).index(n) for n in free]
        err = predicted_errors(A[:, idx], sigma)
        errors.update({n: float(e) for n, e in zip(free, err)})
        may_hold = [k for k, n in enumerate(free) if n not in keep]
        if np.max(err) <= tolerance or not may_hold:
            break
        free.pop(max(may_hold, key=lambda k: err[k]))
    return free, errors


def radius_free(free: Sequence[str], K, b, m, cov, terms, sigma: float,
                tolerance: float, reference=None) -> tuple[bool, float]:
    """Whether the field radius (``radius``, the scale of the whole K) is to be estimated on
    top of the estimated set ``free``, and its predicted error (sensor unit): yes when the
    diagonal of K is not all in ``free`` (it would repeat it), its error is within
    ``tolerance`` and no parameter of ``free`` has its error pushed over the tolerance by it.

    Why: a calibration's field strength is a number the recording measures wherever the
    field it sees differs in size from the one it was made at (a motor field an autopilot's
    calibration in force leaves, another place); held, the difference goes into whatever
    else is fitted (a motor term ~10 % low). ``reference``: as in :func:`choose_free`."""
    if {"K_xx", "K_yy", "K_zz"} <= set(free):
        return False, float("nan")
    _, x, _, normal, D = project(K, b, terms, m, cov)
    A = jacobian([*free, RADIUS], [], x, normal, D, cov, x @ np.asarray(K).T, K)
    if reference is not None:
        A = np.vstack([A, reference.information_rows([*free, RADIUS], K, b, terms, m, cov,
                                                     sigma)])
    err = predicted_errors(A, sigma)
    before = predicted_errors(A[:, :-1], sigma)
    ok = err[-1] <= tolerance and all(e <= max(tolerance, e0) for e, e0 in zip(err, before))
    return bool(ok), float(err[-1])


@dataclass
class HeldFit:
    """Outcome of :func:`held_fit`, sensor units. ``estimated``: {name: (value, σ)} for the
    free core parameters and each added θ (named ``<effect>[k]``)."""

    K: np.ndarray
    b: np.ndarray
    thetas: list
    r: np.ndarray
    x: np.ndarray
    s: np.ndarray
    normal: np.ndarray
    inliers: np.ndarray
    sigma: float
    tau: float
    estimated: dict = field(default_factory=dict)
    iterations: int = 0
    #: How the LM loop (:func:`streamcal.fitting.damped_lm.damped_lm`) ended: ``converged``
    #: (relative cost decrease at most :data:`RTOL`, or nothing to fit), ``stalled`` (no trial
    #: step lowered the cost) or ``max_iter`` (:data:`MAX_ITER` rounds used while the cost
    #: still fell); ``message`` in words.
    status: str = CONVERGED
    message: str = ""
    #: The factor the ``radius`` scaled the given K by (1 when it was held).
    scale: float = 1.0


def held_fit(m: np.ndarray, cov: Mapping[str, np.ndarray], K0, b0, free: Sequence[str],
             held_terms=(), new_terms=(), sigma0: float | None = None,
             reference=None) -> HeldFit:
    """Robust fit of the core parameters ``free`` and the θ of ``new_terms`` ([(term, θ0)]),
    with every other core parameter and the ``held_terms`` ([(term, θ)]) at their values;
    with ``reference`` (:class:`~.reference_rows.ReferenceRows`) its direction residual is a
    second robust block of the cost (:class:`~.reference_rows.JointBlock`)."""
    m = np.asarray(m, float)
    K0, b0 = np.asarray(K0, float), np.asarray(b0, float)
    nf = len(free)
    thetas0 = [np.asarray(t, float) for _, t in new_terms]
    sizes = [len(t) for t in thetas0]
    P = nf + sum(sizes)
    if len(m) <= P + 2:
        raise InsufficientDataError(f"{len(m)} samples cannot determine {P} parameters")

    def unpack(p):
        K, b = shifted(K0, b0, free, p[:nf])
        out, k = [], nf
        for (term, _), t0, size in zip(new_terms, thetas0, sizes):
            out.append((term, t0 + p[k:k + size]))
            k += size
        return K, b, [*held_terms, *out]

    def state(p, x=None):
        K, b, terms = unpack(p)
        r, x, s, normal, D = project(K, b, terms, m, cov, x, 3 if x is not None else GN_ITERATIONS)
        return K, b, terms, r, x, s, normal, D

    p = np.zeros(P)
    K, b, terms, r, x, s, normal, D = state(p)
    sigma = sigma0 or float(np.median(np.abs(s)) * 1.4826) or 1e-9
    tau = CAUCHY_C * sigma

    joint = None
    if reference is not None:
        joint = reference.joint_block(m, cov, tau, len(held_terms), K0)

    def cost(s_):
        return float(np.sum(np.log1p((s_ / tau) ** 2)))

    def total(st):   # both blocks' cost at a state (K, b, terms, r, x, s, …)
        return cost(st[5]) + (0.0 if joint is None else joint.cost(st[0], st[1], st[2]))

    def linearize(p_, st):
        K_, _, terms_, _, x_, s_, normal_, D_ = st
        A = jacobian(free, terms_[len(held_terms):], x_, normal_, D_, cov, x_ @ K_.T, K0)
        w = 1.0 / (1.0 + (s_ / tau) ** 2)
        # einsum, not BLAS: threaded BLAS on these thin (N, ≤30) products spins on a busy
        # machine (9 of 18 s of a 20-minute flight's diagnosis) for a few MFLOP of work
        H = np.einsum("np,nq->pq", A * w[:, None], A)
        grad = -np.einsum("np,n->p", A, w * s_)     # s(p + dp) ≈ s − A dp
        if joint is None:
            return cost(s_), H, grad, x_            # trials re-project from these directions
        c, Hr, gr = joint.linearize(free, K_, st[1], terms_)
        return cost(s_) + c, H + Hr, grad + gr, x_

    def evaluate(p_, x_):
        trial = state(p_, x_)
        return total(trial), trial

    if P == 0:
        it, status, message = 0, CONVERGED, "nothing to fit"
    else:
        st = (K, b, terms, r, x, s, normal, D)
        res = damped_lm(p, st, total(st), linearize=linearize,
                        propose=lambda p_, d: p_ + d, evaluate=evaluate, max_iter=MAX_ITER,
                        rtol=RTOL, damping=DAMPING)
        p, (K, b, terms, r, x, s, normal, D) = res.x, res.aux
        it, status, message = res.iterations, res.status, res.message
    # noise and width re-estimated at the solution; covariance σ̂² (AᵀWA)⁻¹
    inliers = np.abs(s) <= OUTLIER_WIDTHS * tau
    sigma = float(np.sqrt(np.mean(s[inliers] ** 2))) if inliers.sum() > P else sigma
    estimated = {}
    if P:
        A = jacobian(free, terms[len(held_terms):], x, normal, D, cov, x @ K.T, K0)
        w = 1.0 / (1.0 + (s / tau) ** 2)
        H = np.einsum("np,nq->pq", A * w[:, None], A)
        if joint is not None:   # each block at its own width re-estimated at the solution
            H = H + sigma ** 2 * joint.information(free, K, b, terms)
        try:
            Hinv = np.linalg.inv(H)
            sd = sigma * np.sqrt(np.maximum(np.diag(Hinv), 0.0))
        except np.linalg.LinAlgError:
            sd = np.full(P, np.inf)
        values = [entry(K, b, n) for n in free]
        for (term, th) in terms[len(held_terms):]:
            values += list(th)
        labels = [*free]
        for term, th in terms[len(held_terms):]:
            labels += [f"{term.name}[{k}]" for k in range(len(th))]
        estimated = {n: (float(v), float(e)) for n, v, e in zip(labels, values, sd)}
    rn = np.linalg.norm(r, axis=1)
    scale = 1.0 + p[list(free).index(RADIUS)] / field_radius(K0) if RADIUS in free else 1.0
    return HeldFit(K=K, b=b, thetas=[t for _, t in terms[len(held_terms):]], r=r, x=x, s=s,
                   normal=normal, inliers=rn <= OUTLIER_WIDTHS * tau, sigma=sigma, tau=tau,
                   estimated=estimated, iterations=it, status=status, message=message,
                   scale=float(scale))
