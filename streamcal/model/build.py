"""From effect names to effect terms: the registry, needs checking and parameter validation.

Core effects (``hard_iron``, ``scale``, ``soft_iron``) live in ``K`` and ``b``; registration
effects (``mag_accel_misalignment``, ``time_lag``) have their own solver
(:mod:`streamcal.fitting.registration`). Every other catalog effect is a term object fulfilling
:class:`streamcal.model.effect.Effect`. The tables are views of the registry (:mod:`.registry`).
"""
from __future__ import annotations

from typing import Iterable, Mapping

import numpy as np

from ..errors import MissingColumnsError, UnknownEffectError
from .catalog import BY_NAME, CORE_EFFECTS, EFFECT_NAMES, REGISTRATION_EFFECTS, TERMS

_GROUPS = {"accel": ("ax", "ay", "az"), "gyro": ("gx", "gy", "gz"), "temp": ("temp",)}


def check_known(names: Iterable[str]) -> tuple[str, ...]:
    names = tuple(names)
    for name in names:
        if name not in EFFECT_NAMES:
            raise UnknownEffectError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    return names


def build_effects(names: Iterable[str], covariates: Mapping[str, np.ndarray]) -> list:
    """Term objects for the effects in ``names`` that the LM fits (core and registration effects
    are skipped), with their constants (``T0``, ``t0``, channel centring) taken from
    ``covariates`` — (N,) arrays at the magnetometer instants. Raises
    :class:`UnknownEffectError` or :class:`MissingColumnsError`."""
    return [TERMS[n].build(covariates) for n in check_known(names) if n in TERMS]


def missing_columns(names: Iterable[str], track) -> dict[str, list[str]]:
    """``{effect: [missing column, …]}`` for the effects whose needs ``track`` does not meet."""
    def has(col):
        return bool(track.has(col))

    def group_missing(need):
        if need == "aux":
            return [] if list(getattr(track, "aux_names", [])) else ["<an auxiliary column>"]
        return [c for c in _GROUPS.get(need, (need,)) if not has(c)]

    out = {}
    for name in check_known(names):
        info = BY_NAME[name]
        missing = [c for need in info.needs for c in group_missing(need)]
        if info.needs_any and all(group_missing(g) for g in info.needs_any):
            missing.append(" or ".join(f"{g} ({', '.join(_GROUPS[g])})" for g in info.needs_any))
        if missing:
            out[name] = missing
    return out


def stream_columns(names: Iterable[str], groups: Iterable[str]) -> tuple[str, ...]:
    """The columns a stream that provides the column ``groups`` (``"temp"``, ``"accel"``,
    ``"gyro"``) must keep beside the field for the effects ``names``: each effect's ``needs``
    and the first of its ``needs_any`` the stream provides, in the order of ``groups``. Raises
    :class:`MissingColumnsError` naming an effect whose needs the stream cannot meet."""
    groups = tuple(groups)
    wanted = set()
    for name in check_known(names):
        info = BY_NAME[name]
        lacking = [g for g in info.needs if g not in groups]
        offered = [g for g in info.needs_any if g in groups]
        if info.needs_any and not offered:
            lacking.append(" or ".join(info.needs_any))
        if lacking:
            what = ", ".join("an auxiliary channel" if g == "aux" else g for g in lacking)
            raise MissingColumnsError(f"{name} needs {what}, which the sensor does not provide")
        wanted.update(info.needs, offered[:1])
    return tuple(c for g in groups if g in wanted for c in _GROUPS[g])


def check_needs(names: Iterable[str], track) -> None:
    """Raise :class:`MissingColumnsError` naming every effect whose columns ``track`` lacks."""
    missing = missing_columns(names, track)
    if missing:
        raise MissingColumnsError("; ".join(f"effect '{e}' needs column(s) {', '.join(cols)}"
                                            for e, cols in missing.items()))


def validate_effect_params(effects: Mapping[str, Mapping]) -> None:
    """Check the ``effects`` object of a calibration file; ValueError naming effect and key."""

    for name, params in effects.items():
        if name in TERMS:
            TERMS[name].from_params(params)
        elif name in REGISTRATION_EFFECTS:
            BY_NAME[name].validate(params)
        elif name in CORE_EFFECTS:
            raise ValueError(f"{name}: a core effect has no parameters beyond K and b")
        else:
            raise ValueError(f"unknown effect {name!r}")


def terms_from_params(effects: Mapping[str, Mapping]) -> list[tuple[object, np.ndarray]]:
    """``[(term, θ)]`` in physical units (scale 1) for the LM-contract effects of a calibration."""
    out = []
    for name, params in effects.items():
        if name in TERMS:
            term = TERMS[name].from_params(params)
            out.append((term, term.from_physical(params, 1.0)))
    return out
