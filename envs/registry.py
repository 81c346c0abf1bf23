"""Environment families by name: each turns (seed, K, level) into K agent variants."""

from __future__ import annotations

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


def register_family(name: str) -> Callable[[VariantFactory], VariantFactory]:
    """Decorator for a plugin's family: ``factory(*, seed, num_agents, level, **options)``
    returns the K variants (same spaces, different MDPs)."""

    def add(factory: VariantFactory) -> VariantFactory:
        if FAMILIES.get(name, factory) is not factory:
            raise ValueError(f"environment family {name!r} is already registered")
        FAMILIES[name] = factory
        return factory

    return add


def make_variants(
    family: str, *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    """K variants of ``family``; unknown names and bad options raise a clear ValueError."""
    factory = FAMILIES.get(family)
    if factory is None:
        raise UnknownEnvFamilyError(
            f"unknown environment family {family!r}; known: {', '.join(sorted(FAMILIES))}"
        )
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"heterogeneity level must be in [0, 1], got {level!r}")
    try:
        return factory(seed=seed, num_agents=num_agents, level=level, **options)
    except TypeError as error:
        raise ValueError(f"bad options for env family {family!r}: {error}") from None
