"""The sensor model as a sum of effect terms (docs/effects.md, DESIGN §2).

Each effect is declared once, in its own module of :mod:`.effects`
(docs/adding_an_effect.md); :mod:`.registry` holds the declarations (``register``,
``unregister``, ``registered`` for effects of your own) and :mod:`.catalog` the tables built
from them. ``build_effects(names, covariates)`` makes the term objects the LM fits (contract in
:mod:`.effect`), ``invert_model`` applies a calibration with effects, ``check_needs`` and
``validate_effect_params`` guard inputs.
"""
from ..errors import UnknownEffectError
from .build import (build_effects, check_needs, missing_columns, stream_columns,
                    terms_from_params, validate_effect_params)
from .catalog import (BY_NAME, CORE_EFFECTS, EFFECT_NAMES, PLAUSIBILITY_BOUNDS,
                      REGISTRATION_EFFECTS, SIMULATED_EFFECTS, TERMS)
from .declaration import EffectDeclaration, SimEnvironment, SimulatorTruth
from .invert import invert_model
from .registry import declaration, declarations, register, registered, unregister

__all__ = ["BY_NAME", "CORE_EFFECTS", "EFFECT_NAMES", "EffectDeclaration", "PLAUSIBILITY_BOUNDS",
           "REGISTRATION_EFFECTS", "SIMULATED_EFFECTS", "SimEnvironment", "SimulatorTruth",
           "TERMS", "UnknownEffectError", "build_effects", "check_needs", "declaration",
           "declarations", "invert_model", "missing_columns", "register", "registered",
           "stream_columns", "terms_from_params", "unregister", "validate_effect_params"]
