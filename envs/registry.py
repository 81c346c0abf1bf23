"""Environment families by name: each turns (seed, K, level) into K agent variants."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.gym_variant import GymVariant

VariantFactory = Callable[..., list[EnvVariant]]


class UnknownEnvFamilyError(ValueError):
    pass


def _gridworld(*, seed: int, num_agents: int, level: float, **options: Any) -> list[EnvVariant]:
    from fedhpg.envs.gridworld import make_gridworld_variants

    return list(make_gridworld_variants(seed=seed, num_agents=num_agents, level=level, **options))


def _cartpole(
    *, seed: int, num_agents: int, level: float, gamma: float = 0.99, **options: Any
) -> list[EnvVariant]:
    """CartPole-v1 with the pole half-length spread over 0.5 ± 0.4·level (0.1-0.9 at level 1)."""
    if options:
        raise ValueError(f"cartpole does not support the options {sorted(options)}")
    rng = np.random.default_rng([seed, 0xCA27])
    lengths = 0.5 + 0.4 * level * rng.uniform(-1.0, 1.0, size=num_agents)
    return [
        GymVariant(
            family="cartpole",
            index=k,
            gamma=gamma,
            params={"length": float(length)},
            env_id="CartPole-v1",
            attributes={"length": float(length), "polemass_length": 0.1 * float(length)},
        )
        for k, length in enumerate(lengths)
    ]


FAMILIES: dict[str, VariantFactory] = {"gridworld": _gridworld, "cartpole": _cartpole}


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
