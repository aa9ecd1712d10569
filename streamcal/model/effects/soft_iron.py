"""``soft_iron``: the full upper-triangular ``K`` (docs/effects.md)."""
from ..declaration import EffectDeclaration

EFFECT = EffectDeclaration(
    name="soft_iron", meaning="full upper-triangular K: gains, soft iron, non-orthogonality",
    n_params="6", kind="core")
