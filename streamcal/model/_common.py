"""Small helpers shared by the effect terms: covariate lookup and parameter validation."""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..constants import ATTITUDE_COLUMNS
from ..errors import MissingColumnsError

#: Covariate names that are not auxiliary channels (time, temperature, IMU axes, mag axes, the
#: logged attitude).
NON_AUX = frozenset({"t", "temp", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz",
                     *ATTITUDE_COLUMNS})


def column(cov: Mapping[str, np.ndarray], name: str, effect: str) -> np.ndarray:
    """(N,) float covariate ``name``; :class:`MissingColumnsError` naming the effect if absent."""
    if name not in cov:
        raise MissingColumnsError(f"effect '{effect}' needs column '{name}', which the data lacks")
    return np.asarray(cov[name], dtype=float)


def aux_names(cov: Mapping[str, np.ndarray]) -> list[str]:
    """Auxiliary channel names among the covariates, sorted."""
    return sorted(k for k in cov if k not in NON_AUX)


def number(params: Mapping, key: str, effect: str) -> float:
    value = params.get(key) if isinstance(params, Mapping) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{effect}: parameter '{key}' expects a finite number, found {value!r}")
    return float(value)


def vector3(params: Mapping, key: str, effect: str) -> np.ndarray:
    value = params.get(key) if isinstance(params, Mapping) else None
    ok = isinstance(value, (list, tuple)) and len(value) == 3 and all(
        not isinstance(v, bool) and isinstance(v, (int, float)) for v in value)
    if not ok or not np.all(np.isfinite(np.asarray(value, dtype=float))):
        raise ValueError(f"{effect}: parameter '{key}' expects 3 finite numbers, found {value!r}")
    return np.asarray(value, dtype=float)


def only_keys(params: Mapping, keys: tuple[str, ...], effect: str) -> None:
    if not isinstance(params, Mapping):
        raise ValueError(f"{effect}: expected an object of parameters, found {type(params).__name__}")
    unknown = sorted(set(params) - set(keys))
    if unknown:
        raise ValueError(f"{effect}: unknown parameter(s) {', '.join(map(repr, unknown))}; "
                         f"expected {', '.join(keys)}")


def same_constant(mine: float, theirs: float, key: str, effect: str) -> None:
    if not np.isclose(mine, theirs, rtol=1e-12, atol=1e-12):
        raise ValueError(f"{effect}: parameter '{key}'={theirs} differs from this term's {key}={mine}; "
                         f"build the term from the parameters instead")
