"""The effect catalog of docs/effects.md as views of the registry (:mod:`.registry`): names
(part of the interface), kinds and declarations, always current.

``needs`` of a declaration lists track columns; ``"aux"`` means at least one auxiliary channel,
and ``("gyro", "accel")`` in ``needs_any`` means either group of columns will do.
"""
from __future__ import annotations

from .registry import NameView, TableView

#: Every effect name, in catalog order.
EFFECT_NAMES = NameView(lambda d: True)
#: Effects carried by K and b themselves.
CORE_EFFECTS = NameView(lambda d: d.kind == "core")
#: Effects the gravity-/gyro-tied solver fits (:mod:`streamcal.fitting.registration`).
REGISTRATION_EFFECTS = NameView(lambda d: d.kind == "registration")
#: Effect name → term class (the LM contract of :mod:`.effect`).
TERMS = TableView(lambda d: d.kind == "term", lambda d: d.term)
#: Effect name → its :class:`~.declaration.EffectDeclaration`.
BY_NAME = TableView(lambda d: True, lambda d: d)
#: Effect name → plausibility bound (fraction of the field radius) of every term effect.
PLAUSIBILITY_BOUNDS = TableView(lambda d: d.kind == "term", lambda d: d.bound)
#: Effects the simulator can inject, in catalog order (:mod:`streamcal.sim`).
SIMULATED_EFFECTS = NameView(lambda d: d.simulated is not None)
