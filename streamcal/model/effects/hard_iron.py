"""``hard_iron``: the constant offset ``b`` of every calibration (docs/effects.md)."""
from ..declaration import EffectDeclaration

EFFECT = EffectDeclaration(name="hard_iron", meaning="constant offset b", n_params="3", kind="core")
