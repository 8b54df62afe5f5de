"""Registries of the attacks and defenses: the seam through which a new one is added.

A :class:`Registry` maps names to objects of one kind (a mixing rule, a mitigation, ...) with a one-line
description each. The modules that define the things create their registry and register into it, e.g.::

    MITIGATIONS: Registry[Mitigation] = Registry("defense", "mitigation")

    @MITIGATIONS.register("fine_tuning", "PPO on clean episodes only")
    def fine_tuning(ctx): ...

and the code that dispatches on a name looks it up with :meth:`Registry.get`, which names the known ones when the
name is unknown. Every registry created is listed by :func:`registries` (``seqtrojan attacks``, ``seqtrojan
defenses``) once its module is imported.

The bottom of the package: this module imports only :mod:`seqtrojan.errors`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar, overload

from seqtrojan.errors import ConfigError

T = TypeVar("T")

Family = Literal["attack", "defense", "model"]
FAMILIES: tuple[Family, ...] = ("attack", "defense", "model")


@dataclass(frozen=True)
class Entry(Generic[T]):
    """One registered thing."""

    name: str
    kind: str
    """what it is: trigger, mixing, reward, monitor, detector, mitigation"""
    description: str
    """one line"""
    obj: T


class Registry(Generic[T]):
    """Names -> objects of one ``kind`` of one ``family`` (attack, defense, or model: the sequence-model cells), in
    registration order."""

    def __init__(self, family: Family, kind: str) -> None:
        if family not in FAMILIES:
            raise ConfigError(f"registry family must be one of {list(FAMILIES)}, got {family!r}")
        self.family, self.kind = family, kind
        self._entries: dict[str, Entry[T]] = {}
        _ALL.append(self)

    @overload
    def register(self, name: str, description: str) -> Callable[[T], T]: ...

    @overload
    def register(self, name: str, description: str, obj: T) -> T: ...

    def register(self, name: str, description: str, obj: T | None = None) -> T | Callable[[T], T]:
        """Register ``obj`` as ``name``: ``register(name, description, obj)``, or as a decorator
        ``@register(name, description)``. A name already taken is refused (:class:`ConfigError`). The decorator
        gives the decorated object the registry's type ``T``: register a function with extra (defaulted)
        parameters with the call form after its definition, so that its own signature is kept."""

        def add(target: T) -> T:
            if not name or not name.isidentifier():
                raise ConfigError(f"a {self.kind} name must be an identifier, got {name!r}")
            if not description or "\n" in description:
                raise ConfigError(f"{self.kind} {name!r} needs a one-line description, got {description!r}")
            if name in self._entries:
                raise ConfigError(f"{self.kind} {name!r} is already registered ({self._entries[name].description})")
            self._entries[name] = Entry(name, self.kind, description, target)
            return target

        return add if obj is None else add(obj)

    def entry(self, name: str) -> Entry[T]:
        try:
            return self._entries[name]
        except KeyError:
            raise ConfigError(f"unknown {self.kind} {name!r}; known: {', '.join(self._entries) or 'none'}") from None

    def get(self, name: str) -> T:
        """The object registered as ``name``; :class:`ConfigError` listing the known names for an unknown one."""
        return self.entry(name).obj

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def names(self) -> tuple[str, ...]:
        return tuple(self._entries)

    def items(self) -> tuple[tuple[str, T], ...]:
        return tuple((name, e.obj) for name, e in self._entries.items())

    def entries(self) -> tuple[Entry[T], ...]:
        return tuple(self._entries.values())

    def __repr__(self) -> str:
        return f"Registry({self.family!r}, {self.kind!r}: {', '.join(self._entries)})"


_ALL: list[Registry] = []


def registries(family: Family | None = None) -> tuple[Registry, ...]:
    """Every registry created so far (of ``family``), in creation order. A registry exists once the module that
    defines it is imported."""
    return tuple(r for r in _ALL if family is None or r.family == family)
