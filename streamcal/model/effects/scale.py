"""``scale``: per-axis gains only, a diagonal ``K`` (docs/effects.md)."""
from ..declaration import EffectDeclaration

EFFECT = EffectDeclaration(name="scale", meaning="per-axis gain only (diagonal K)", n_params="3",
                           kind="core")
