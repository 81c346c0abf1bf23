"""Environment families by name: each turns (seed, K, level) into K agent variants.

``env.family`` is a registered name (the package's own, or one a plugin module registered
with :func:`register_family`), a name an installed package offers through the entry-point
group ``fedhpg.env_families``, or a dotted path ``package.module:factory``. Every host resolves
the name itself, so a remote agent needs only the same package or module installed.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Callable
from typing import Any

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.families import GYM_FAMILIES

VariantFactory = Callable[..., list[EnvVariant]]


class UnknownEnvFamilyError(ValueError):
    pass


def _gridworld(*, seed: int, num_agents: int, level: float, **options: Any) -> list[EnvVariant]:
    from fedhpg.envs.gridworld import make_gridworld_variants

    return list(make_gridworld_variants(seed=seed, num_agents=num_agents, level=level, **options))


FAMILIES: dict[str, VariantFactory] = {"gridworld": _gridworld, **GYM_FAMILIES}
FAMILY_ENTRY_POINTS = "fedhpg.env_families"
"""Entry-point group through which an installed package offers families by name."""


def register_family(name: str) -> Callable[[VariantFactory], VariantFactory]:
    """Decorator for a plugin's family: ``factory(*, seed, num_agents, level, **options)``
    returns the K variants (same spaces, different MDPs)."""

    def add(factory: VariantFactory) -> VariantFactory:
        if FAMILIES.get(name, factory) is not factory:
            raise ValueError(f"environment family {name!r} is already registered")
        FAMILIES[name] = factory
        return factory

    return add


def _import_dotted(path: str) -> VariantFactory:
    module_name, _, attribute = path.partition(":")
    try:
        factory = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise UnknownEnvFamilyError(f"cannot import environment family {path!r}: {error}") from None
    if not callable(factory):
        raise UnknownEnvFamilyError(f"environment family {path!r} is not a function")
    return factory


def _installed_names() -> list[str]:
    return [entry.name for entry in importlib.metadata.entry_points(group=FAMILY_ENTRY_POINTS)]


def _from_entry_points(name: str) -> VariantFactory | None:
    """Loaded on first use only: importing an installed plugin costs nothing until it is named."""
    for entry in importlib.metadata.entry_points(group=FAMILY_ENTRY_POINTS, name=name):
        try:
            factory = entry.load()
        except (ImportError, AttributeError) as error:
            raise UnknownEnvFamilyError(
                f"cannot load environment family {name!r} ({entry.value}): {error}"
            ) from None
        FAMILIES.setdefault(name, factory)
        return FAMILIES[name]
    return None


def resolve_family(family: str) -> VariantFactory:
    """The factory ``family`` names (see the module's docstring), or UnknownEnvFamilyError."""
    factory = FAMILIES.get(family)
    if factory is None and ":" in family:
        factory = _import_dotted(family)
    if factory is None:
        factory = _from_entry_points(family)
    if factory is None:
        known = sorted({*FAMILIES, *_installed_names()})
        raise UnknownEnvFamilyError(
            f"unknown environment family {family!r}; known: {', '.join(known)} "
            "(or a dotted path package.module:factory)"
        )
    return factory


def make_variants(
    family: str, *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    """K variants of ``family``; unknown names and bad options raise a clear ValueError."""
    factory = resolve_family(family)
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"heterogeneity level must be in [0, 1], got {level!r}")
    try:
        return factory(seed=seed, num_agents=num_agents, level=level, **options)
    except TypeError as error:
        raise ValueError(f"bad options for env family {family!r}: {error}") from None
