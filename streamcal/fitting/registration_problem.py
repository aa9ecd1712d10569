"""Residuals and Jacobians of the gravity-tied model (equation (1) of
:mod:`streamcal.fitting.registration`): the direction x_j = Rᵀ(cos δ ĝ_j + sin δ h_j) of each
sample from the down direction ĝ_j at its true instant t_j − τ, and the reading
K x_j + b + Σ f. Parameters are packed as (K upper triangle (6), b (3), effect terms, rotation
increment ε (3) when the misalignment is fitted, δ, τ when the lag is fitted)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: Central-difference step (s) of the τ column of the Jacobian.
LAG_STEP = 1e-3
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


class _Problem:
    """Residuals and Jacobians of (1) over the samples ``m`` (N,3)."""

    def __init__(self, m, cov, gref, terms, fit_rot, fit_lag):
        self.m, self.cov, self.gref, self.terms = m, cov, gref, terms
        self.fit_rot, self.fit_lag = fit_rot, fit_lag
        self.sizes = [t.n_params() for t in terms]
        self.t = np.asarray(cov["t"], dtype=float)
        self._down: dict[float, tuple] = {}

    def pack(self, K, b, thetas, dip, lag):
        p = [K[tuple(zip(*_UPPER))], b, *thetas]
        if self.fit_rot:
            p.append(np.zeros(3))
        p.append([dip])
        if self.fit_lag:
            p.append([lag])
        return np.concatenate([np.ravel(v) for v in p]).astype(float)

    def unpack(self, p, R0, lag0):
        K = np.zeros((3, 3))
        K[tuple(zip(*_UPPER))] = p[:6]
        b, i = p[6:9], 9
        thetas = []
        for n in self.sizes:
            thetas.append(p[i:i + n])
            i += n
        R = R0
        if self.fit_rot:
            R = R0 @ Rotation.from_rotvec(p[i:i + 3]).as_matrix()
            i += 3
        dip = p[i]
        lag = p[i + 1] if self.fit_lag else lag0
        return K, b, thetas, R, dip, lag

    def down(self, lag):
        """(ĝ (N,3), trust (N,)) at the samples' instants minus ``lag``; read-only arrays,
        cached per lag (an LM pass asks for the same lag hundreds of times)."""
        key = float(lag)
        hit = self._down.get(key)
        if hit is None:
            if len(self._down) >= 4:   # a lag fit moves on: keep the cache small
                self._down.clear()
            hit = self.gref.at(self.t - lag)
            for a in hit:
                a.setflags(write=False)
            self._down[key] = hit
        return hit

    def model(self, K, b, thetas, x):
        u = x @ K.T
        g = u + b
        A = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
        for term, th in zip(self.terms, thetas):
            g = g + term.term(th, u, self.cov)
            ju = term.jac_u(th, u, self.cov)
            if ju is not None:
                A += ju
        return g, A

    @staticmethod
    def direction(R, dip, g, h):
        h = h - np.einsum("ni,ni->n", h, g)[:, None] * g
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        return (np.cos(dip) * g + np.sin(dip) * h) @ R, h

    def residual(self, K, b, thetas, R, dip, lag, h):
        g, _ = self.down(lag)
        x, _ = self.direction(R, dip, g, h)
        return self.model(K, b, thetas, x)[0] - self.m

    def headings(self, K, b, thetas, R, dip, lag, h=None, gn_steps=2):
        """Step (a): best heading per sample (N,3) ⟂ ĝ_j."""
        g, _ = self.down(lag)
        target = self.m - b
        u0 = target - sum((t.term(th, target, self.cov) for t, th in zip(self.terms, thetas)),
                          np.zeros_like(target))
        y = u0 @ (R @ np.linalg.inv(K)).T                          # R K⁻¹(m − b − Σf)
        h = y - np.einsum("ni,ni->n", y, g)[:, None] * g
        small = np.linalg.norm(h, axis=1) < 1e-9
        if small.any():  # reading along gravity: any heading is as good
            h[small] = np.cross(g[small], [0.37, 0.48, 0.79])
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        for _ in range(gn_steps):
            x, h = self.direction(R, dip, g, h)
            r, A = self.model(K, b, thetas, x)
            r -= self.m
            side = np.cross(g, h)
            J = np.einsum("nij,nj->ni", A, (np.sin(dip) * side @ R) @ K.T)
            step = -np.einsum("ni,ni->n", J, r) / np.maximum(np.einsum("ni,ni->n", J, J), 1e-300)
            h = np.cos(step)[:, None] * h + np.sin(step)[:, None] * side
        return h

    def reduced_normal(self, K, b, thetas, R, dip, lag, h, r, w):
        """Gauss–Newton normal equations (P,P), (P,) of the weighted residual over p with each
        sample's heading eliminated (Schur complement of the 1×1 heading blocks):

            J̃_j = Π_j J_p,j,   Π_j = I − a_j a_jᵀ / ‖a_j‖²,   a_j = ∂r_j/∂φ_j
            H = Σ w_j J̃_jᵀ J̃_j,   g = Σ w_j J̃_jᵀ r_j
        """
        g, _ = self.down(lag)
        x, hh = self.direction(R, dip, g, h)
        _, A = self.model(K, b, thetas, x)
        a = np.einsum("nij,nj->ni", A @ K, (np.sin(dip) * np.cross(g, hh)) @ R)
        a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300)
        J = self.jacobian(K, b, thetas, R, dip, lag, h)
        J = J - a[:, :, None] * np.einsum("ni,nip->np", a, J)[:, None, :]
        Jw = J * w[:, None, None]
        H = np.einsum("nip,niq->pq", Jw, J)
        return H, np.einsum("nip,ni->p", Jw, r)

    def jacobian(self, K, b, thetas, R, dip, lag, h):
        """(N,3,P) derivative of the residual with respect to the packed parameters."""
        g, _ = self.down(lag)
        x, hh = self.direction(R, dip, g, h)
        u = x @ K.T
        _, A = self.model(K, b, thetas, x)
        cols = []
        for a, c in _UPPER:
            e = np.zeros((len(x), 3))
            e[:, a] = x[:, c]
            cols.append(np.einsum("nij,nj->ni", A, e))
        cols += [np.broadcast_to(np.eye(3)[:, k], (len(x), 3)) for k in range(3)]
        for term, th in zip(self.terms, thetas):
            jt = term.jac_theta(th, u, self.cov)
            cols += [jt[:, :, k] for k in range(jt.shape[2])]
        AK = A @ K
        if self.fit_rot:
            for k in range(3):
                cols.append(np.einsum("nij,nj->ni", AK, np.cross(x, np.eye(3)[k])))
        dx = (-np.sin(dip) * g + np.cos(dip) * hh) @ R
        cols.append(np.einsum("nij,nj->ni", AK, dx))
        if self.fit_lag:
            rp = self.residual(K, b, thetas, R, dip, lag + LAG_STEP, h)
            rm = self.residual(K, b, thetas, R, dip, lag - LAG_STEP, h)
            cols.append((rp - rm) / (2 * LAG_STEP))
        return np.stack(cols, axis=2)
