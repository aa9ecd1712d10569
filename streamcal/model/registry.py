"""The registry of effect declarations: the built-in ones (:mod:`.effects`) and any a user
registers, in order. Every table of effects in the program is a view of it, so a registered
effect is a catalog effect everywhere at once (``fit --add``, the calibration file, the
diagnosis' candidates, the report) and an unregistered one nowhere.

    from streamcal.model import registered
    with registered(MY_EFFECT):
        cal = streamcal.fit(track, add=["my_effect"])

The views (:class:`NameView`, :class:`TableView`) read the registry on every use, so a name
imported once (``from streamcal.model import EFFECT_NAMES``) follows later registrations.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from typing import Callable, Iterator

from ..errors import UnknownEffectError
from .declaration import EffectDeclaration
from .effects import BUILTIN

_DECLARED: dict[str, EffectDeclaration] = {d.name: d for d in BUILTIN}
#: Bumped by every change, so the views rebuild their tables only then (a fit asks them a few
#: dozen times).
_version = 0


def declarations() -> tuple[EffectDeclaration, ...]:
    """Every declared effect, built-in ones first, in catalog order."""
    return tuple(_DECLARED.values())


def declaration(name: str) -> EffectDeclaration:
    """The declaration of effect ``name``; :class:`UnknownEffectError` naming the known ones."""
    try:
        return _DECLARED[name]
    except (KeyError, TypeError):
        raise UnknownEffectError(f"unknown effect {name!r}; known: {', '.join(_DECLARED)}") \
            from None


def register(effect: EffectDeclaration) -> EffectDeclaration:
    """Add ``effect`` (a ``term`` effect: core and registration effects need their own
    solver) to the catalog; ValueError when its name is taken or the declaration is
    inconsistent. Returns it, so a module may write ``EFFECT = register(EffectDeclaration(…))``."""
    if not isinstance(effect, EffectDeclaration):
        raise ValueError(f"register expects an EffectDeclaration, found {type(effect).__name__}")
    effect.check()
    if effect.kind != "term":
        raise ValueError(f"effect {effect.name!r}: only term effects can be registered; "
                         f"{effect.kind} effects need their own solver")
    if effect.name in _DECLARED:
        raise ValueError(f"effect {effect.name!r} is already declared")
    global _version
    _DECLARED[effect.name] = effect
    _version += 1
    return effect


def unregister(name: str) -> None:
    """Remove the registered effect ``name``; ValueError for a built-in one."""
    if any(d.name == name for d in BUILTIN):
        raise ValueError(f"effect {name!r} is built in and cannot be unregistered")
    global _version
    declaration(name)
    del _DECLARED[name]
    _version += 1


@contextmanager
def registered(effect: EffectDeclaration) -> Iterator[EffectDeclaration]:
    """Register ``effect`` for the ``with`` block; unregistered on the way out, also on error."""
    register(effect)
    try:
        yield effect
    finally:
        unregister(effect.name)


class NameView(Sequence):
    """A read-only, always current sequence of effect names."""

    def __init__(self, select: Callable[[EffectDeclaration], bool]):
        self._select = select
        self._cache: tuple[int, tuple[str, ...]] = (-1, ())

    def _names(self) -> tuple[str, ...]:
        version, names = self._cache
        if version != _version:
            names = tuple(d.name for d in _DECLARED.values() if self._select(d))
            self._cache = (_version, names)
        return names

    def __getitem__(self, index):
        return self._names()[index]

    def __len__(self) -> int:
        return len(self._names())

    def __iter__(self):
        return iter(self._names())

    def __contains__(self, name) -> bool:
        return name in self._names()

    def __eq__(self, other) -> bool:
        return isinstance(other, (tuple, list, NameView)) and tuple(self) == tuple(other)

    def __hash__(self):
        return hash(self._names())

    def __add__(self, other):
        return self._names() + tuple(other)

    def __radd__(self, other):
        return tuple(other) + self._names()

    def __repr__(self) -> str:
        return repr(self._names())


class TableView(Mapping):
    """A read-only, always current mapping ``name → value(declaration)`` over the effects
    ``select`` accepts."""

    def __init__(self, select: Callable[[EffectDeclaration], bool],
                 value: Callable[[EffectDeclaration], object]):
        self._select, self._value = select, value
        self._cache: tuple[int, dict] = (-1, {})

    def _table(self) -> dict:
        version, table = self._cache
        if version != _version:
            table = {d.name: self._value(d) for d in _DECLARED.values() if self._select(d)}
            self._cache = (_version, table)
        return table

    def __getitem__(self, name):
        return self._table()[name]

    def __contains__(self, name) -> bool:
        return name in self._table()

    def __len__(self) -> int:
        return len(self._table())

    def __iter__(self):
        return iter(self._table())

    def __repr__(self) -> str:
        return repr(self._table())
