"""The sensor model as a sum of effect terms (SPEC §3, DESIGN §2)."""
from .catalog import BY_NAME, CATALOG, CORE_EFFECTS, EFFECT_NAMES, EffectInfo

__all__ = ["BY_NAME", "CATALOG", "CORE_EFFECTS", "EFFECT_NAMES", "EffectInfo"]
