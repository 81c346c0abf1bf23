"""Names in the config that pick code: a small registry, and typed options parsed from plain maps.

Algorithms (``algo.name``), server strategies (``strategy.name``) and environment families
(``env.family``) are registry entries; so are the choices of
:mod:`fedhpg.common.configuration.vocabularies` (attacks, estimators, baselines, clocks, round
policies). The package's own algorithms and strategies are the modules of one sub-package (found
with :mod:`pkgutil`, so adding one is adding its file); a user adds more from outside by importing a
module that registers them, named in ``plugins=[my.module]``.

Options of an entry (``algo.params``, ``strategy.params``, one agent's ``agents.budget``) are a
frozen dataclass of the entry's own; :func:`parse_options` builds it from the composed map and
names the first bad key in a :class:`~fedhpg.common.configuration.config_error.ConfigError`. Pure
Python: no torch.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import pkgutil
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from typing import Any, Generic, TypeVar

from fedhpg.common.configuration.config_error import ConfigError

T = TypeVar("T")
OptionsT = TypeVar("OptionsT")


class Registry(Generic[T]):
    """Entries by name; the package's own are imported from ``package`` on first use."""

    def __init__(
        self, what: str, key: str, package: str | None = None, *, in_order: bool = False
    ) -> None:
        self.what = what
        """What an entry is, for messages ('algorithm')."""
        self.key = key
        """The config key that names an entry ('algo.name')."""
        self._package = package
        self._entries: dict[str, T] = {}
        self._discovered = package is None
        self._in_order = in_order
        """Names listed in the order they were registered (a vocabulary lists its built-in
        choices first, in the order its messages always gave them), not sorted."""

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator: ``@ALGORITHMS.register("fedhpg")``. A name is taken once."""

        def add(entry: T) -> T:
            known = self._entries.get(name)
            if known is not None and known is not entry:
                raise ValueError(f"{self.what} {name!r} is already registered ({known!r})")
            self._entries[name] = entry
            return entry

        return add

    def _discover(self) -> None:
        if self._discovered or self._package is None:
            return
        self._discovered = True
        package = importlib.import_module(self._package)
        for module in pkgutil.iter_modules(package.__path__):
            if not module.name.startswith("_"):
                importlib.import_module(f"{self._package}.{module.name}")

    def names(self) -> list[str]:
        self._discover()
        return list(self._entries) if self._in_order else sorted(self._entries)

    def get(self, name: str) -> T:
        """The entry, or a ConfigError naming ``key`` and the known names."""
        self._discover()
        entry = self._entries.get(name)
        if entry is None:
            raise ConfigError(
                self.key,
                f"no {self.what} {name!r}; known: {', '.join(self.names())} "
                "(a plugin module can register more: plugins=[module])",
            )
        return entry

    def __iter__(self) -> Iterator[tuple[str, T]]:
        return iter([(name, self._entries[name]) for name in self.names()])


def import_plugins(modules: list[str]) -> None:
    """Import the user's modules that register entries; a bad name is a ConfigError."""
    for index, name in enumerate(modules):
        try:
            importlib.import_module(name)
        except ImportError as error:
            raise ConfigError(f"plugins[{index}]", f"cannot import {name!r}: {error}") from None


# --- options: plain map -> frozen dataclass -----------------------------------------------------


class OptionError(ValueError):
    """An option's value is wrong; ``field`` names it (raised by options' ``__post_init__``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def _fits(value: Any, hint: Any) -> tuple[bool, Any]:
    """(whether ``value`` fits the annotation, the value converted: an int for a float)."""
    if hint is Any:
        return True, value
    if hint is None or hint is type(None):
        return value is None, value
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        for option in typing.get_args(hint):
            ok, converted = _fits(value, option)
            if ok:
                return True, converted
        return False, value
    if origin is typing.Literal:
        return value in typing.get_args(hint), value
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return (ok and math.isfinite(value)), float(value) if ok else value
    if hint is str:
        return isinstance(value, str), value
    if origin in (list, tuple) or hint in (list, tuple):
        if not isinstance(value, list | tuple):
            return False, value
        args = typing.get_args(hint)
        item_hint = args[0] if args else Any
        converted = []
        for item in value:
            ok, item = _fits(item, item_hint)
            if not ok:
                return False, value
            converted.append(item)
        return True, tuple(converted) if origin is tuple or hint is tuple else converted
    if origin is dict or hint is dict:
        return isinstance(value, Mapping), dict(value) if isinstance(value, Mapping) else value
    return isinstance(value, hint), value


def _hint_name(hint: Any) -> str:
    if typing.get_origin(hint) is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


_HINTS: dict[type, dict[str, Any]] = {}


def _type_hints(cls: type) -> dict[str, Any]:
    """``typing.get_type_hints``, once per class: it evaluates every annotation string again
    on each call, and a host of thousands of agents parses options per agent it meets."""
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    return hints


def parse_options(cls: type[OptionsT], values: Mapping[str, Any] | None, key: str) -> OptionsT:
    """``cls(**values)`` with every key known and every value of its field's type.

    Missing keys take the dataclass defaults. ``key`` is the config path of the map
    ('algo.params'); errors name ``key.field``.
    """
    values = dict(values or {})
    hints = _type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields))
    if unknown:
        allowed = ", ".join(sorted(fields)) or "none"
        raise ConfigError(f"{key}.{unknown[0]}", f"unknown option; allowed: {allowed}")
    converted: dict[str, Any] = {}
    for name, value in values.items():
        ok, value = _fits(value, hints[name])
        if not ok:
            raise ConfigError(
                f"{key}.{name}", f"got {values[name]!r}, must be {_hint_name(hints[name])}"
            )
        converted[name] = value
    try:
        return cls(**converted)
    except OptionError as error:
        raise ConfigError(f"{key}.{error.field}", str(error)) from None
    except TypeError as error:  # a field without default left out
        raise ConfigError(key, str(error)) from None


def options_dict(options: object) -> dict[str, Any]:
    """A frozen options dataclass as the plain map :func:`parse_options` takes back."""
    return dataclasses.asdict(options)  # type: ignore[call-overload]
