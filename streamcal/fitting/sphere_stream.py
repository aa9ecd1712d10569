"""One-pass sphere fit from running sums (Gauss–Newton on sufficient statistics).

The residual of sample ``x_i`` (sensor unit, (3,)) for centre ``c`` and per-axis radii ``s`` is
the algebraic residual of the seed "Gauss–Newton for sphere fitting (3 of 3)":

    r_i = 1 − Σ_k u_ik² / s_k²,          u_i = x_i − c

with Jacobian rows ``∂r/∂c_j = 2 u_ij / s_j²`` and ``∂r/∂s_j = 2 u_ij² / s_j³``. Every entry of
``JᵀJ`` and ``Jᵀr`` is a sum over samples of ``u_j^a u_k^b`` with ``a, b ∈ {0, 1, 2}``, and those
centred sums follow from the raw sums of the table below for *any* ``c`` (expand the powers of
``x − c``). So one pass over the data keeps

    N                       1
    S1_j   = Σ x_j          3
    S2_jk  = Σ x_j x_k      6 (symmetric)
    S21_jk = Σ x_j² x_k     9
    S22_jk = Σ x_j² x_k²    6 (symmetric)

25 numbers (we store the symmetric 3×3 blocks whole for vectorized code), and Gauss–Newton
iterates on them without ever looking at the data again: O(1) memory, one pass.

The same shift formula moves the sums to another origin. Sums are kept relative to an origin
taken from the first batch (mean of its samples) so that the fourth powers do not swamp the
centred moments with cancellation when the offset is large compared with the radius; ``merge``
uses the shift to add statistics gathered around different origins.

The sphere model (one radius ``R``, ``K = R·I``) is the axis model with ``s = (R, R, R)``: its
Jacobian is ``J P`` with ``P`` mapping 4 parameters to 6. The start point is the linear
("Kåsa") sphere fit, whose normal equations use the same sums.
"""
from __future__ import annotations

import numpy as np

from ..errors import InsufficientDataError

#: Gauss–Newton stops when the step is below this fraction of the radius.
_STEP_TOL = 1e-10
_MAX_ITER = 50
#: Normal matrices with a larger condition number mean the directions cannot fix the fit.
_MAX_COND = 1e12

# P maps sphere parameters (c0, c1, c2, R) to axis parameters (c0, c1, c2, s0, s1, s2).
_P_SPHERE = np.zeros((6, 4))
_P_SPHERE[[0, 1, 2], [0, 1, 2]] = 1.0
_P_SPHERE[3:, 3] = 1.0


class SphereStats:
    """Running sufficient statistics of (N,3) samples for a Gauss–Newton sphere fit.

    Memory is fixed (25 numbers plus an origin), whatever the number of samples::

        stats = SphereStats()
        stats.update(m)            # m (n,3) in the sensor unit; rows with NaN are skipped
        center, radius = stats.fit()
    """

    __slots__ = ("n", "origin", "s1", "s2", "s21", "s22")

    def __init__(self):
        self.origin: np.ndarray | None = None
        self.reset()

    def reset(self) -> None:
        """Forget every sample (keeps nothing, not even the origin)."""
        self.origin = None
        self.n = 0
        self.s1 = np.zeros(3)
        self.s2 = np.zeros((3, 3))
        self.s21 = np.zeros((3, 3))
        self.s22 = np.zeros((3, 3))

    def update(self, m) -> int:
        """Add the samples ``m`` (n,3) (or (3,)); rows with a non-finite value are skipped.
        Returns the number of samples added."""
        x = np.asarray(m, dtype=float).reshape(-1, 3)
        x = x[np.isfinite(x).all(axis=1)]
        if not len(x):
            return 0
        if self.origin is None:
            self.origin = x.mean(axis=0)
        xq = np.empty((len(x), 6))
        np.subtract(x, self.origin, out=xq[:, :3])
        np.multiply(xq[:, :3], xq[:, :3], out=xq[:, 3:])
        G = xq.T @ xq                          # one product: [x q]ᵀ[x q], q = x²
        self.n += len(x)
        self.s1 += xq[:, :3].sum(axis=0)
        self.s2 += G[:3, :3]
        self.s21 += G[3:, :3]
        self.s22 += G[3:, 3:]
        return len(x)

    def merge(self, other: "SphereStats") -> "SphereStats":
        """Add the samples summarised by ``other`` (in place); returns ``self``."""
        if other.n == 0:
            return self
        if self.origin is None:
            self.origin = other.origin.copy()
        n, s1, s2, s21, s22 = _shifted(other.n, other.s1, other.s2, other.s21, other.s22,
                                       self.origin - other.origin)
        self.n += n
        self.s1 += s1
        self.s2 += s2
        self.s21 += s21
        self.s22 += s22
        return self

    def copy(self) -> "SphereStats":
        out = SphereStats()
        if self.origin is not None:
            out.origin = self.origin.copy()
        out.n = self.n
        out.s1, out.s2, out.s21, out.s22 = (self.s1.copy(), self.s2.copy(), self.s21.copy(),
                                            self.s22.copy())
        return out

    # -- fitting ------------------------------------------------------------------------------
    def fit(self, tol: float = _STEP_TOL, max_iter: int = _MAX_ITER) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius (sensor unit) of the least-squares sphere for the residual
        ``1 − ‖x − c‖²/R²``. Raises :class:`InsufficientDataError` when the samples cannot
        determine a sphere (fewer than 4, or all on a plane/cap too small).

        ``tol``: stop when the step is below this fraction of the radius; ``max_iter``: at most
        this many iterations (a running estimate that only frames directions may stop early)."""
        center, s = self._gauss_newton(_P_SPHERE, tol, max_iter)
        return center, float(s[0])

    def fit_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre (3,) and per-axis radii (3,) of the axis-aligned ellipsoid (the seed's
        six-parameter model)."""
        return self._gauss_newton(np.eye(6))

    def cost(self, center, radii) -> float:
        """``Σ r_i²`` at the given centre (3,) and radii (scalar or (3,)), from the sums."""
        self._need(4)
        radii = np.broadcast_to(np.asarray(radii, dtype=float), (3,))
        _, m1, m2, m21, m22 = _shifted(self.n, self.s1, self.s2, self.s21, self.s22,
                                       np.asarray(center, dtype=float) - self.origin)
        a = radii ** -2.0
        return float(self.n - 2.0 * a @ np.diag(m2) + a @ m22 @ a)

    def _need(self, k: int) -> None:
        if self.n < k:
            raise InsufficientDataError(f"sphere fit needs at least {k} samples, has {self.n}")

    def _kasa(self) -> tuple[np.ndarray, float]:
        # ‖x‖² = 2 c·x + d, d = R² − ‖c‖²: linear least squares, normal equations from the sums.
        A = np.empty((4, 4))
        A[:3, :3] = 4.0 * self.s2
        A[:3, 3] = A[3, :3] = 2.0 * self.s1
        A[3, 3] = self.n
        rhs = np.empty(4)
        rhs[:3] = 2.0 * self.s21.sum(axis=0)      # Σ_i 2 x_ij ‖x_i‖²
        rhs[3] = np.trace(self.s2)                # Σ_i ‖x_i‖²
        if np.linalg.cond(A) > _MAX_COND:
            raise InsufficientDataError(
                f"sphere fit: the {self.n} samples do not span a sphere (too few directions)")
        sol = np.linalg.solve(A, rhs)
        c = sol[:3]
        r2 = sol[3] + c @ c
        if not r2 > 0:
            raise InsufficientDataError("sphere fit: samples do not determine a radius")
        return c, float(np.sqrt(r2))

    def _gauss_newton(self, P: np.ndarray, tol: float = _STEP_TOL,
                      max_iter: int = _MAX_ITER) -> tuple[np.ndarray, np.ndarray]:
        self._need(P.shape[1])
        c, R = self._kasa()                                  # relative to the origin
        beta = np.concatenate([c, [R, R, R]]) if P.shape[1] == 6 else np.concatenate([c, [R]])
        cost = self._cost_at(P @ beta)
        for _ in range(max_iter):
            JtJ, Jtr = self._normal(P @ beta)
            A, g = P.T @ JtJ @ P, P.T @ Jtr
            if not np.all(np.isfinite(A)) or np.linalg.cond(A) > _MAX_COND:
                raise InsufficientDataError(
                    f"sphere fit: the {self.n} samples leave the fit undetermined (too few directions)")
            step = -np.linalg.solve(A, g)
            scale = float(np.abs(beta[3:]).max())
            # Step halving keeps the cost decreasing when far from the minimum.
            while np.linalg.norm(step) > tol * scale:
                trial = beta + step
                full = P @ trial
                trial_cost = self._cost_at(full) if np.all(full[3:] > 0) else np.inf
                if trial_cost <= cost:
                    beta, cost = trial, trial_cost
                    break
                step = step / 2.0
            if np.linalg.norm(step) <= tol * scale:
                break
        full = P @ beta
        return full[:3] + self.origin, full[3:].copy()

    def _cost_at(self, beta6: np.ndarray) -> float:
        _, m1, m2, m21, m22 = _shifted(self.n, self.s1, self.s2, self.s21, self.s22, beta6[:3])
        a = beta6[3:] ** -2.0
        return float(self.n - 2.0 * a @ np.diag(m2) + a @ m22 @ a)

    def _normal(self, beta6: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``JᵀJ`` (6,6) and ``Jᵀr`` (6,) of the axis model at ``beta6`` (origin-relative)."""
        _, m1, m2, m21, m22 = _shifted(self.n, self.s1, self.s2, self.s21, self.s22, beta6[:3])
        s = beta6[3:]
        a = s ** -2.0
        b = s ** -3.0
        JtJ = np.empty((6, 6))
        JtJ[:3, :3] = 4.0 * np.outer(a, a) * m2
        JtJ[:3, 3:] = 4.0 * np.outer(a, b) * m21.T          # Σ u_j u_k² = m21[k, j]
        JtJ[3:, :3] = JtJ[:3, 3:].T
        JtJ[3:, 3:] = 4.0 * np.outer(b, b) * m22
        Jtr = np.empty(6)
        Jtr[:3] = 2.0 * a * (m1 - a @ m21)                  # Σ_k a_k Σ u_k² u_j
        Jtr[3:] = 2.0 * b * (np.diag(m2) - m22 @ a)
        return JtJ, Jtr


def _shifted(n, s1, s2, s21, s22, c):
    """Raw sums of ``x`` → the same sums of ``u = x − c`` (c (3,))."""
    c = np.asarray(c, dtype=float)
    d2 = np.diag(s2)                                        # Σ x_j²
    m1 = s1 - n * c
    m2 = s2 - np.outer(c, s1) - np.outer(s1, c) + n * np.outer(c, c)
    # Σ u_j² u_k = Σ (x_j² − 2c_j x_j + c_j²)(x_k − c_k)
    m21 = (s21 - np.outer(d2, c) - 2.0 * c[:, None] * s2 + 2.0 * np.outer(c * s1, c)
           + np.outer(c * c, s1) - n * np.outer(c * c, c))
    # Σ u_j² u_k² = Σ (x_j² − 2c_j x_j + c_j²)(x_k² − 2c_k x_k + c_k²)
    m22 = (s22 - 2.0 * s21 * c[None, :] - 2.0 * (s21 * c[None, :]).T
           + np.outer(d2, c * c) + np.outer(c * c, d2) + 4.0 * np.outer(c, c) * s2
           - 2.0 * np.outer(c * s1, c * c) - 2.0 * np.outer(c * c, c * s1)
           + n * np.outer(c * c, c * c))
    return n, m1, m2, m21, m22


def fit_sphere_stream(m) -> tuple[np.ndarray, np.ndarray]:
    """One-pass sphere fit of samples ``m`` (N,3): returns ``(K, b)`` with ``K = R·I`` (3,3)
    and ``b`` the centre (3,), both in the sensor unit (used by ``fit(m, method="sphere_stream")``)."""
    stats = SphereStats()
    stats.update(m)
    center, radius = stats.fit()
    return radius * np.eye(3), center


def sphere_spread(m) -> float | None:
    """How far samples ``m`` (N,3, sensor unit; non-finite rows skipped) lie from one sphere:
    ``1.4826 × median |‖m − c‖/R − 1|`` (relative, a robust σ) about the one-pass sphere fit
    ``(c, R)`` of :class:`SphereStats`; None when fewer than 10 samples or no sphere fits."""
    m = np.asarray(m, dtype=float)
    m = m[np.isfinite(m).all(axis=1)]
    if len(m) < 10:
        return None
    stats = SphereStats()
    stats.update(m)
    try:
        c, R = stats.fit()
    except (InsufficientDataError, np.linalg.LinAlgError, ValueError):
        return None
    if not (np.all(np.isfinite(c)) and np.isfinite(R) and R > 0):
        return None
    return 1.4826 * float(np.median(np.abs(np.linalg.norm(m - c, axis=1) / R - 1.0)))
