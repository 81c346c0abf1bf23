"""Families that build their variants per agent index (the protocol of ``fedhpg.envs.registry``).

A run of K agents rarely needs all K variants in one process: each agent host needs its own,
the server a few. A :class:`LazyFamily` answers both calls, the K-list one and the per-index
one, from one function that makes the variants of some indices.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from fedhpg.envs.base import EnvVariant


class VariantsAt(Protocol):
    def __call__(
        self, indices: Sequence[int], /, *, seed: int, num_agents: int, level: float, **options: Any
    ) -> list[EnvVariant]: ...


@dataclass(frozen=True)
class LazyFamily:
    """A family whose ``variants_at(indices, ...)`` makes the variants of ``indices`` alone;
    called like a plain family (``seed``, ``num_agents``, ``level``, options) it makes all K."""

    variants_at: VariantsAt

    def __call__(
        self, *, seed: int, num_agents: int, level: float, **options: Any
    ) -> list[EnvVariant]:
        return self.variants_at(
            range(num_agents), seed=seed, num_agents=num_agents, level=level, **options
        )


def per_index_family(variant: Callable[..., EnvVariant]) -> LazyFamily:
    """A family from ``variant(index, *, seed, num_agents, level, **options)``: agent
    ``index``'s variant, which must not depend on which other indices are asked for."""

    def variants_at(
        indices: Sequence[int], /, *, seed: int, num_agents: int, level: float, **options: Any
    ) -> list[EnvVariant]:
        return [
            variant(k, seed=seed, num_agents=num_agents, level=level, **options) for k in indices
        ]

    return LazyFamily(variants_at)
