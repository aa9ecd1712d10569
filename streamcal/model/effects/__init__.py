"""The built-in effects, one module each, in catalog order (docs/effects.md); each module's
``EFFECT`` is its :class:`~streamcal.model.declaration.EffectDeclaration`."""
from . import (aux_interference, axis_nonlinearity, hard_iron, mag_accel_misalignment, scale,
               soft_iron, temperature_offset, temperature_scale, time_drift, time_lag)

#: Catalog order: it orders the catalog, the candidates tried and the simulator's random draws.
BUILTIN = tuple(m.EFFECT for m in (
    hard_iron, scale, soft_iron, temperature_offset, temperature_scale, time_drift,
    aux_interference, axis_nonlinearity, mag_accel_misalignment, time_lag))
