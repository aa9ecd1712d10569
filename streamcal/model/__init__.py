"""The sensor model as a sum of effect terms (docs/effects.md, DESIGN §2).

``build_effects(names, covariates)`` makes the term objects the LM fits (contract in
:mod:`.effect`), ``invert_model`` applies a calibration with effects, ``check_needs`` and
``validate_effect_params`` guard inputs.
"""
from ..errors import UnknownEffectError
from .build import (REGISTRATION_EFFECTS, TERMS, build_effects, check_needs, missing_columns,
                    terms_from_params, validate_effect_params)
from .catalog import BY_NAME, CATALOG, CORE_EFFECTS, EFFECT_NAMES, EffectInfo
from .invert import invert_model

__all__ = ["BY_NAME", "CATALOG", "CORE_EFFECTS", "EFFECT_NAMES", "EffectInfo",
           "REGISTRATION_EFFECTS", "TERMS", "UnknownEffectError", "build_effects", "check_needs",
           "invert_model", "missing_columns", "terms_from_params", "validate_effect_params"]
