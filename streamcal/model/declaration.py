"""What one effect declares, in one place (docs/adding_an_effect.md).

An :class:`EffectDeclaration` holds data and small functions only; the code that uses each
piece reads it from the registry (:mod:`.registry`) instead of keeping its own table:

================  ==========================================  ===================================
piece             field                                        read by
================  ==========================================  ===================================
catalog entry     ``name``, ``meaning``, ``n_params``, ``kind``  every name check, ``fit --help``
residual term     ``term`` (the :class:`.effect.Effect` class)   the LM, ``Calibration.apply``
needs             ``needs``, ``needs_any``                     :func:`.build.missing_columns`
units             ``units``, ``notes``                         :mod:`streamcal.units`, the report
plausibility      ``bound``                                    :mod:`streamcal.diagnosis.effect_plausibility`
evidence wording  ``subject``, ``tied_evidence``               :mod:`streamcal.diagnosis.candidates`
simulator truth   ``simulated``                                :mod:`streamcal.sim`
================  ==========================================  ===================================
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np

#: ``kind`` of an effect: carried by ``K`` and ``b`` (``core``), a term of the LM contract
#: (``term``), or fitted by the gravity-/gyro-tied solver (``registration``).
KINDS = ("core", "term", "registration")

#: Plausibility bound of an effect that does not state one: its field may be as large as the
#: field radius.
DEFAULT_BOUND = 1.0


class SimEnvironment(NamedTuple):
    """The simulated session an effect's truth parameters may refer to."""

    field_uT: float     #: Earth field strength, µT
    dip_deg: float      #: inclination below the horizon, degrees
    T0_C: float         #: temperature at which ``K`` and ``b`` hold, °C
    t0_s: float         #: time at which ``K`` and ``b`` hold, s


@dataclass(frozen=True)
class SimulatorTruth:
    """How :func:`streamcal.sim.simulate` injects an effect.

    ``draw``: ``"vector"`` (the user gives a magnitude, the simulator a random direction of that
    norm, or the user gives the (3,) vector) or ``"scalar"`` (the number itself).
    ``params(value, env)``: the truth parameters in the calibration-file layout, ``value`` the
    (3,) vector or the scalar, ``env`` a :class:`SimEnvironment`.
    ``field(u, cov, params)``: (N,3) field the effect adds to the reading (µT), ``u`` (N,3) the
    undistorted reading ``K x``, ``cov`` the true columns at the sampling instants (``t``,
    ``temp``, ``motor_current``); None when the effect is not an added field (registration
    effects: the scenario applies them to the motion and the clock) — or, for a ``term``
    effect, to use the declared term itself.
    ``magnitude``: what the user's number means, for the docs (``"|c|, µT/°C"``).
    ``limit``: largest allowed ``|value|`` of a scalar draw (with ``limit_unit``), or None.
    """

    draw: str
    params: Callable[[Any, SimEnvironment], dict]
    field: Callable[[np.ndarray, Mapping[str, np.ndarray], Mapping], np.ndarray] | None = None
    magnitude: str = ""
    limit: float | None = None
    limit_unit: str = ""


@dataclass(frozen=True, eq=False)
class EffectDeclaration:
    """One effect of the catalog, every piece the program knows about it (module doc).

    ``name``: the interface name (``fit --add NAME``, the calibration file key).
    ``meaning``: one line for the catalog; ``n_params``: parameter count as shown (``"3"``,
    ``"3 per channel"``).
    ``kind``: one of :data:`KINDS`.
    ``term``: for ``kind == "term"``, the class fulfilling :class:`streamcal.model.effect.Effect`
    with a class attribute ``name`` equal to ``name``.
    ``needs``: track columns the effect needs (``"temp"``; groups ``"accel"``, ``"gyro"``;
    ``"aux"`` = at least one auxiliary channel; any other column by its name); ``needs_any``:
    groups of which one will do.
    ``units``: parameter key → unit, ``{u}`` standing for the sensor unit (``"{u}/°C"``);
    angles in ``rad`` and times in ``s`` are shown in ° and ms/µs. ``notes``: parameter key →
    what its number means, shown beside the unit in the report.
    ``bound``: largest plausible rms of the effect's field at the recording's points, as a
    fraction of the field radius (diagnosis against a calibration).
    ``subject``: what the residual follows when the effect is missing, as in "residual follows
    temp (r=0.82)"; a string, or a function of the built term; "" means the effect's name.
    ``tied_evidence(params, kind)``: for a registration effect, the text appended to its
    "gravity-tied rms a → b µT" evidence from its fitted parameters (``kind`` "gravity" or
    "gyro").
    ``validate(params)``: for effects without a term class, ValueError naming the effect and
    key when the calibration file's parameters are malformed.
    ``simulated``: how the simulator injects it (:class:`SimulatorTruth`), or None.
    """

    name: str
    meaning: str
    n_params: str
    kind: str = "term"
    term: type | None = None
    needs: tuple[str, ...] = ()
    needs_any: tuple[str, ...] = ()
    units: Mapping[str, str] = field(default_factory=dict)
    notes: Mapping[str, str] = field(default_factory=dict)
    bound: float = DEFAULT_BOUND
    subject: str | Callable[[Any], str] = ""
    tied_evidence: Callable[[Mapping, str], str] | None = None
    validate: Callable[[Mapping], None] | None = None
    simulated: SimulatorTruth | None = None

    def evidence_subject(self, term) -> str:
        """What "residual follows …" names for this effect's built ``term``."""
        subject = self.subject(term) if callable(self.subject) else self.subject
        return subject or self.name

    def check(self) -> None:
        """ValueError when the declaration is inconsistent (a registry refuses it)."""
        if not self.name.isidentifier():
            raise ValueError(f"effect name {self.name!r} must be a Python identifier "
                             "(letters, digits, underscores): it is written in comma lists")
        if self.kind not in KINDS:
            raise ValueError(f"effect {self.name!r}: kind must be one of {', '.join(KINDS)}, "
                             f"found {self.kind!r}")
        if self.kind == "term":
            if self.term is None or getattr(self.term, "name", None) != self.name:
                raise ValueError(f"effect {self.name!r}: a term effect needs a term class whose "
                                 f"name is {self.name!r}")
        if not self.bound > 0:
            raise ValueError(f"effect {self.name!r}: bound must be positive, found {self.bound!r}")
        if self.simulated is not None and self.simulated.draw not in ("vector", "scalar"):
            raise ValueError(f"effect {self.name!r}: simulated.draw must be 'vector' or "
                             f"'scalar', found {self.simulated.draw!r}")
