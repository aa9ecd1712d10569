"""What the terms linear in one covariate share (``time_drift``, ``temperature_offset``,
``temperature_scale``): ``Δ = cov[COLUMN] − ref`` with ``ref`` the median of the covariate in the
data the term was built from (stored under the key ``REF``), so the constant part stays in ``b`` /
``K``, and one 3-vector parameter ``PARAM``.

The default term is an offset, ``f_j = θ Δ_j`` (θ in the sensor unit per unit of the covariate;
normalization divides it by ``scale``); a gain (``temperature_scale``) overrides the term, its
Jacobians and the physical form.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ._common import column, number, only_keys, same_constant, vector3

_EYE = np.eye(3)


class LinearTerm:
    """An offset ``θ (cov[COLUMN] − ref)``; subclasses set ``name``, ``COLUMN``, ``REF``, ``PARAM``."""

    name = ""
    COLUMN = ""
    REF = ""
    PARAM = ""

    def __init__(self, ref: float):
        self.ref = float(ref)

    @classmethod
    def build(cls, cov: Mapping[str, np.ndarray]):
        return cls(float(np.nanmedian(column(cov, cls.COLUMN, cls.name))))

    @classmethod
    def from_params(cls, params: Mapping):
        only_keys(params, (cls.REF, cls.PARAM), cls.name)
        vector3(params, cls.PARAM, cls.name)
        return cls(number(params, cls.REF, cls.name))

    def n_params(self) -> int:
        return 3

    def initial(self) -> np.ndarray:
        return np.zeros(3)

    def delta(self, cov) -> np.ndarray:
        """(N,) covariate minus the reference."""
        return column(cov, self.COLUMN, self.name) - self.ref

    def term(self, theta, u, cov):
        return self.delta(cov)[:, None] * np.asarray(theta)[None, :]

    def jac_theta(self, theta, u, cov):
        return self.delta(cov)[:, None, None] * _EYE[None]

    def jac_u(self, theta, u, cov):
        return None

    def to_physical(self, theta, scale: float) -> dict:
        return {self.REF: self.ref, self.PARAM: [float(v) for v in np.asarray(theta) * scale]}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        return self._physical_vector(params) / scale

    def _physical_vector(self, params: Mapping) -> np.ndarray:
        same_constant(self.ref, number(params, self.REF, self.name), self.REF, self.name)
        return vector3(params, self.PARAM, self.name)
