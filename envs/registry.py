"""Environment families by name: each turns (seed, K, level) into K agent variants.

``env.family`` is a registered name (the package's own, or one a plugin module registered
with :func:`register_family`), a name an installed package offers through the entry-point
group ``fedhpg.env_families``, or a dotted path ``package.module:factory``. Every host resolves
the name itself, so a remote agent needs only the same package or module installed.

A family is a function ``factory(*, seed, num_agents, level, **options) -> list[EnvVariant]``
(all K variants). A run of K = 10 000 agents asks for one agent's variant at a time (each host
for its own, the server for the few it needs), so a family may also offer them per index:

- decorate a function ``variant(index, *, seed, num_agents, level, **options) -> EnvVariant``
  with :func:`per_index_family` (it still answers the K-list call, building the list from it);
- or give the factory an attribute ``variants_at(indices, *, seed, num_agents, level,
  **options) -> list[EnvVariant]`` (a :class:`LazyFamily` built by hand), for a family that
  draws several indices more cheaply together, as the built-in ones do.

Variant k must then equal ``factory(..., num_agents=K)[k]``. A family that offers only the
K-list works unchanged: :func:`make_variants_at` builds its K variants once and keeps the last
few lists (see ``EAGER_CACHE_SIZE``), which costs K variants of memory and time per run.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.families import GYM_FAMILIES
from fedhpg.envs.gridworld import gridworld_variants_at
from fedhpg.envs.gym_family import gym_family
from fedhpg.envs.lazy import LazyFamily, VariantsAt, per_index_family

VariantFactory = Callable[..., list[EnvVariant]]
EAGER_CACHE_SIZE = 4
"""K-lists kept of families without ``variants_at`` (one run asks with one key; a few cover
tests and hosts that build the variants of several runs)."""


class UnknownEnvFamilyError(ValueError):
    pass


def _gridworld_at(
    indices: Sequence[int], /, *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    return list(
        gridworld_variants_at(indices, seed=seed, num_agents=num_agents, level=level, **options)
    )


FAMILIES: dict[str, VariantFactory] = {
    "gridworld": LazyFamily(_gridworld_at),
    **GYM_FAMILIES,
    "gym": gym_family,
}
FAMILY_ENTRY_POINTS = "fedhpg.env_families"
"""Entry-point group through which an installed package offers families by name."""


def register_family(name: str) -> Callable[[VariantFactory], VariantFactory]:
    """Decorator for a plugin's family: ``factory(*, seed, num_agents, level, **options)``
    returns the K variants (same spaces, different MDPs); a :class:`LazyFamily` (e.g. from
    :func:`per_index_family`, applied first) also makes one index at a time."""

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
    if isinstance(factory, type) and issubclass(factory, gym.Env):
        raise UnknownEnvFamilyError(
            f"{path} is a gymnasium environment, not a family of variants: run it with env=gym "
            "env.id=<its registered id> (and env.vary for what differs between agents)"
        )
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
    if factory is None and family in gym.registry:
        raise UnknownEnvFamilyError(
            f"{family!r} is a gymnasium id, not an environment family: run it with env=gym "
            f"env.id={family}"
        )
    if factory is None:
        known = sorted({*FAMILIES, *_installed_names()})
        raise UnknownEnvFamilyError(
            f"unknown environment family {family!r}; known: {', '.join(known)} "
            "(or a dotted path package.module:factory)"
        )
    return factory


def _check_level(level: float) -> None:
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"heterogeneity level must be in [0, 1], got {level!r}")


def make_variants(
    family: str, *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    """K variants of ``family``; unknown names and bad options raise a clear ValueError."""
    factory = resolve_family(family)
    _check_level(level)
    try:
        return factory(seed=seed, num_agents=num_agents, level=level, **options)
    except TypeError as error:
        raise ValueError(f"bad options for env family {family!r}: {error}") from None


def per_index(factory: VariantFactory) -> VariantsAt | None:
    """The family's ``variants_at`` if it offers one (see the module's docstring)."""
    variants_at = getattr(factory, "variants_at", None)
    return variants_at if callable(variants_at) else None


_EAGER: OrderedDict[tuple[Any, ...], list[EnvVariant]] = OrderedDict()


def _all_variants(
    family: str, factory: VariantFactory, seed: int, num_agents: int, level: float, options: Any
) -> list[EnvVariant]:
    """The K-list of a family without ``variants_at``, built once per (family, seed, K, level,
    options) and kept among the last :data:`EAGER_CACHE_SIZE` ones."""
    # The factory itself in the key: a name registered anew (tests, reloads) is a new family.
    options_key = json.dumps(options, sort_keys=True, default=repr)
    key = (factory, family, seed, num_agents, level, options_key)
    if key in _EAGER:
        _EAGER.move_to_end(key)
        return _EAGER[key]
    variants = factory(seed=seed, num_agents=num_agents, level=level, **options)
    if len(variants) != num_agents:
        raise ValueError(
            f"env family {family!r} made {len(variants)} variants, not num_agents={num_agents}"
        )
    _EAGER[key] = variants
    while len(_EAGER) > EAGER_CACHE_SIZE:
        _EAGER.popitem(last=False)
    return variants


def make_variants_at(
    family: str,
    indices: Sequence[int],
    *,
    seed: int,
    num_agents: int,
    level: float,
    **options: Any,
) -> list[EnvVariant]:
    """The variants of agents ``indices`` (in that order) of a K-agent run, each equal to
    ``make_variants(...)[k]``; built alone where the family offers ``variants_at``."""
    factory = resolve_family(family)
    _check_level(level)
    outside = [k for k in indices if not 0 <= k < num_agents]
    if outside:
        raise IndexError(f"agent index {outside[0]} is not in [0, num_agents={num_agents})")
    variants_at = per_index(factory)
    try:
        if variants_at is not None:
            return list(
                variants_at(indices, seed=seed, num_agents=num_agents, level=level, **options)
            )
        every = _all_variants(family, factory, seed, num_agents, level, options)
    except TypeError as error:
        raise ValueError(f"bad options for env family {family!r}: {error}") from None
    return [every[k] for k in indices]


def make_variant(
    family: str, index: int, *, seed: int, num_agents: int, level: float, **options: Any
) -> EnvVariant:
    """Agent ``index``'s variant of a K-agent run (:func:`make_variants_at` of one index)."""
    return make_variants_at(
        family, [index], seed=seed, num_agents=num_agents, level=level, **options
    )[0]


__all__ = [
    "FAMILIES",
    "FAMILY_ENTRY_POINTS",
    "LazyFamily",
    "UnknownEnvFamilyError",
    "VariantFactory",
    "make_variant",
    "make_variants",
    "make_variants_at",
    "per_index_family",
    "register_family",
    "resolve_family",
]
