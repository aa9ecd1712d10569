"""The part of a diagnosis that only a diagnosis against a held calibration has
(:attr:`streamcal.diagnosis.result.Diagnosis.held`; None for a fresh fit): which parameters were
held, which re-estimated, where the held values came from. A value: frozen, its containers
read-only (:func:`streamcal.values.freeze`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Mapping

from ...calibration import jsonable
from ...values import FrozenDict, fields_equal, freeze

#: The diagnosis' JSON keys of the held part, in the order ``diagnose --json`` writes them
#: (after the keys every diagnosis has); ``held`` marks a held diagnosis.
JSON_KEYS = ("held", "estimated", "predicted_sigma", "tolerance", "calibration_source",
             "n_ranked", "aux_channels", "fit_status", "held_after_fit", "suspicious",
             "gyro_pinned", "gyro_link", "held_attitude_reference")


@dataclass(frozen=True, eq=False)
class HeldPart:
    """What a diagnosis against a given (or the stated default) calibration adds; values in the
    sensor unit. Equal when every field is (:func:`streamcal.values.same`)."""

    #: The parameters kept at their given values (core entries such as ``K_xy``, then effects
    #: of the calibration); the JSON key ``held``.
    parameters: tuple[str, ...] = ()
    #: Each re-estimated parameter: ``{"value", "sigma"}`` (σ from σ̂²(AᵀWA)⁻¹).
    estimated: Mapping = field(default_factory=FrozenDict)
    #: The Cramér–Rao error each parameter had when the held set was chosen.
    predicted_sigma: Mapping = field(default_factory=FrozenDict)
    #: The bound a predicted error had to meet to be re-estimated (sensor unit).
    tolerance: float = float("nan")
    #: Where the held values came from (a file, "autopilot …", "default …").
    calibration_source: str = ""
    #: Samples the candidate refits (and ladder steps after the first) used; 0: every one.
    n_ranked: int = 0
    #: ``{channel: r}``: how closely the base model's residual (every sample) follows each
    #: auxiliary channel alone (:func:`streamcal.diagnosis.held.aux_channels.channel_scores`),
    #: largest first.
    aux_channels: Mapping = field(default_factory=FrozenDict)
    #: How the held fit's LM loop ended: ``{"status", "iterations", "message"}``.
    fit_status: Mapping = field(default_factory=FrozenDict)
    #: Parameters held by the re-check at the fitted point
    #: (:func:`streamcal.diagnosis.held.recheck.settle`), in order, each with the value and σ
    #: it had and why.
    held_after_fit: tuple = ()
    #: Kept parameters (b without a calibration) that failed that re-check.
    suspicious: Mapping = field(default_factory=FrozenDict)
    #: Held parameters the gyro link pinned instead (:mod:`streamcal.diagnosis.held.gyro_pin`):
    #: ``{name: {"value", "sigma", "held_value"}}``; ``gyro_link`` how that was decided.
    gyro_pinned: Mapping = field(default_factory=FrozenDict)
    gyro_link: Mapping = field(default_factory=FrozenDict)
    #: The attitude reference the held fit used beside the magnitude
    #: (:meth:`streamcal.diagnosis.held.reference_rows.ReferenceRows.describe`); empty without
    #: one (and then not in the JSON).
    attitude_reference: Mapping = field(default_factory=FrozenDict)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, freeze(getattr(self, f.name)))

    def __eq__(self, other) -> bool:
        if not isinstance(other, HeldPart):
            return NotImplemented
        return fields_equal(self, other)

    __hash__ = None   # holds mappings and floats compared NaN-safe

    def json_fields(self, n: int) -> dict:
        """The JSON keys :data:`JSON_KEYS` (``n``: the diagnosis' samples, the ``n_ranked`` of
        a ranking over every one); the containers are this value's own, read-only."""
        return {"held": self.parameters, "estimated": self.estimated,
                "predicted_sigma": self.predicted_sigma, "tolerance": self.tolerance,
                "calibration_source": self.calibration_source,
                "n_ranked": int(self.n_ranked or n), "aux_channels": self.aux_channels,
                "fit_status": self.fit_status, "held_after_fit": self.held_after_fit,
                "suspicious": self.suspicious, "gyro_pinned": jsonable(self.gyro_pinned),
                "gyro_link": jsonable(self.gyro_link),
                **({"held_attitude_reference": jsonable(self.attitude_reference)}
                   if self.attitude_reference else {})}

    @classmethod
    def from_dict(cls, d: Mapping) -> "HeldPart | None":
        """The held part of a diagnosis' JSON ``d``; None when ``d`` has no ``held`` (a fresh
        diagnosis). A null ``tolerance`` comes back as NaN."""
        if "held" not in d:
            return None
        tol = d.get("tolerance")
        return cls(parameters=tuple(d["held"]), estimated=d.get("estimated", {}),
                   predicted_sigma=d.get("predicted_sigma", {}),
                   tolerance=float("nan") if tol is None else float(tol),
                   calibration_source=d.get("calibration_source", ""),
                   n_ranked=int(d.get("n_ranked", 0)), aux_channels=d.get("aux_channels", {}),
                   fit_status=d.get("fit_status", {}),
                   held_after_fit=d.get("held_after_fit", ()),
                   suspicious=d.get("suspicious", {}), gyro_pinned=d.get("gyro_pinned", {}),
                   gyro_link=d.get("gyro_link", {}),
                   attitude_reference=d.get("held_attitude_reference", {}))
