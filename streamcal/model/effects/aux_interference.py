"""``aux_interference`` (docs/effects.md): interference from auxiliary channels.

For channels ``a_k`` (motor current, PWM duty…, any numeric track column that is not time,
temperature or an IMU axis) the term is

    f_j = Σ_k g_k z_jk,      z_jk = (a_jk − a0_k) / σ_k

with ``a0_k`` the channel median and ``σ_k`` its standard deviation (1 when constant): the fit
sees centred, unit-spread channels so its parameters are well conditioned whatever the channel's
unit. Parameters are reported per channel in physical units, ``g_k / σ_k`` in sensor unit per
unit of the channel, with ``a0_k``:

    {"channels": {"motor_current": {"a0": 0.8, "g": [gx, gy, gz]}}}

θ is ordered channel by channel, (g_1x, g_1y, g_1z, g_2x, …).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ...errors import MissingColumnsError
from ..declaration import EffectDeclaration, SimulatorTruth
from .._common import aux_names, column, number, only_keys, same_constant, vector3


class AuxInterference:
    """Field proportional to one or more auxiliary channels."""

    name = "aux_interference"

    def __init__(self, channels: Sequence[str], a0: Sequence[float], sigma: Sequence[float]):
        self.channels = tuple(channels)
        self.a0 = np.asarray(a0, dtype=float).reshape(len(self.channels))
        self.sigma = np.asarray(sigma, dtype=float).reshape(len(self.channels))

    @classmethod
    def build(cls, cov: Mapping[str, np.ndarray], channels: Sequence[str] | None = None):
        channels = aux_names(cov) if channels is None else list(channels)
        if not channels:
            raise MissingColumnsError(f"effect '{cls.name}' needs at least one auxiliary column")
        values = [column(cov, c, cls.name) for c in channels]
        a0 = [float(np.nanmedian(v)) for v in values]
        sigma = [float(np.nanstd(v)) or 1.0 for v in values]
        return cls(channels, a0, sigma)

    @classmethod
    def from_params(cls, params: Mapping) -> "AuxInterference":
        only_keys(params, ("channels",), cls.name)
        chans = params.get("channels")
        if not isinstance(chans, Mapping) or not chans:
            raise ValueError(f"{cls.name}: parameter 'channels' expects a non-empty object "
                             "{channel: {\"a0\": number, \"g\": [3 numbers]}}")
        a0 = []
        for name, p in chans.items():
            where = f"{cls.name}.channels.{name}"
            only_keys(p, ("a0", "g"), where)
            vector3(p, "g", where)
            a0.append(number(p, "a0", where))
        return cls(list(chans), a0, np.ones(len(a0)))

    def n_params(self) -> int:
        return 3 * len(self.channels)

    def initial(self) -> np.ndarray:
        return np.zeros(self.n_params())

    def _z(self, cov) -> np.ndarray:
        """(N,C) centred, scaled channels."""
        a = np.stack([column(cov, c, self.name) for c in self.channels], axis=1)
        return (a - self.a0) / self.sigma

    def term(self, theta, u, cov):
        return self._z(cov) @ np.asarray(theta).reshape(-1, 3)

    def jac_theta(self, theta, u, cov):
        z = self._z(cov)
        # ∂f_i/∂g_ki = z_k: block (N,3,C,3) with an identity over the axis pair.
        jac = z[:, None, :, None] * np.eye(3)[None, :, None, :]
        return jac.reshape(len(z), 3, 3 * len(self.channels))

    def jac_u(self, theta, u, cov):
        return None

    def to_physical(self, theta, scale: float) -> dict:
        g = np.asarray(theta).reshape(-1, 3) * scale / self.sigma[:, None]
        return {"channels": {c: {"a0": float(a), "g": [float(v) for v in gk]}
                             for c, a, gk in zip(self.channels, self.a0, g)}}

    def from_physical(self, params: Mapping, scale: float) -> np.ndarray:
        chans = params.get("channels") if isinstance(params, Mapping) else None
        if not isinstance(chans, Mapping) or set(chans) != set(self.channels):
            raise ValueError(f"{self.name}: parameters must name the channels "
                             f"{', '.join(self.channels)}")
        out = []
        for c, a0, sigma in zip(self.channels, self.a0, self.sigma):
            where = f"{self.name}.channels.{c}"
            same_constant(a0, number(chans[c], "a0", where), "a0", where)
            out.append(vector3(chans[c], "g", where) * sigma / scale)
        return np.concatenate(out)


def _sim_field(u, cov, p):
    out = np.zeros_like(u)
    for channel, ch in p["channels"].items():
        out += (cov[channel] - ch["a0"])[:, None] * np.asarray(ch["g"])
    return out


EFFECT = EffectDeclaration(
    name="aux_interference", meaning="field proportional to an auxiliary channel",
    n_params="3 per channel", term=AuxInterference, needs=("aux",),
    units={"a0": "channel unit", "g": "{u} per channel unit"},
    # An added field as large as the Earth's: the compass would not point at all (ArduPilot's
    # compassmot already calls interference above 60 % of the field unacceptable).
    bound=1.0,
    subject=lambda term: ", ".join(term.channels),
    simulated=SimulatorTruth(
        "vector", lambda v, env: {"channels": {"motor_current": {"a0": 0.0, "g": v.tolist()}}},
        _sim_field, magnitude="|g|, µT/A (sensor frame); needs motor=True"))
