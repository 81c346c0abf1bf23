"""A run's K environment variants, and the settings each agent derives from its own.

Variants are made per agent index (:func:`variant_of`, :func:`variants_of`): at K = 10 000 an
agent host builds its own agents' variants and the server the few it needs, never the K-long
list. :func:`run_variants` is the K variants as a lazy sequence, each built when it is read.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, overload

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.env import GYM_FAMILY
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.registry import make_variants_at

ITERATION_CHUNK = 1024
"""Variants made together while iterating :class:`RunVariants` (one draw of their rows)."""


def variants_of(run: RunConfig, indices: Iterable[int]) -> dict[int, EnvVariant]:
    """The variants of agents ``indices``, by index (deterministic in env.* and the seed)."""
    wanted = list(dict.fromkeys(int(k) for k in indices))
    env = run.env
    made = make_variants_at(
        env.family,
        wanted,
        seed=run.seed if env.seed is None else env.seed,
        num_agents=run.agents.num_agents,
        level=env.level,
        **family_options(run),
    )
    return dict(zip(wanted, made, strict=True))


def family_options(run: RunConfig) -> dict[str, Any]:
    """What the env family's factory takes besides (seed, K, level): ``env.options``, and for
    the gym family ``env.id``, ``env.kwargs``, ``env.vary`` and ``env.horizon`` (its episodes'
    step limit, which may exceed the id's registered one)."""
    env = run.env
    if env.family != GYM_FAMILY:
        return dict(env.options)
    gym_keys: dict[str, Any] = {"id": env.id, "kwargs": env.kwargs, "vary": env.vary}
    gym_keys["max_episode_steps"] = env.horizon
    return {**env.options, **{key: value for key, value in gym_keys.items() if value}}


def variant_of(run: RunConfig, index: int) -> EnvVariant:
    """Agent ``index``'s variant; IndexError outside [0, K)."""
    return variants_of(run, [index])[index]


class RunVariants(Sequence[EnvVariant]):
    """The K variants of a run, each made when read (never all held): ``variants[k]`` is
    :func:`variant_of`, iteration makes them :data:`ITERATION_CHUNK` at a time."""

    def __init__(self, run: RunConfig) -> None:
        self.run = run

    def __len__(self) -> int:
        return self.run.agents.num_agents

    @overload
    def __getitem__(self, index: int) -> EnvVariant: ...

    @overload
    def __getitem__(self, index: slice) -> list[EnvVariant]: ...

    def __getitem__(self, index: int | slice) -> EnvVariant | list[EnvVariant]:
        if isinstance(index, slice):
            indices = range(len(self))[index]
            return list(variants_of(self.run, indices).values())
        k = index + len(self) if index < 0 else index
        if not 0 <= k < len(self):
            raise IndexError(f"agent index {index} is not in [0, {len(self)})")
        return variant_of(self.run, k)

    def __iter__(self) -> Iterator[EnvVariant]:
        for first in range(0, len(self), ITERATION_CHUNK):
            yield from self[first : first + ITERATION_CHUNK]

    def __repr__(self) -> str:
        return f"RunVariants({self.run.env.family!r}, K={len(self)})"


def run_variants(run: RunConfig) -> RunVariants:
    """The K environment variants of a run (deterministic in env.* and the seed), made lazily."""
    return RunVariants(run)


def training_horizon(run: RunConfig, variant: EnvVariant) -> int:
    """H: ``env.horizon``, else the variant's episode step limit."""
    return run.env.horizon or variant.max_episode_steps


def discount(run: RunConfig, variant: EnvVariant) -> float:
    """γ_k: ``env.gamma`` for every agent, else the variant's own."""
    return run.env.gamma if run.env.gamma is not None else variant.gamma


def variant_digest(run: RunConfig, variant: EnvVariant) -> str:
    """The fingerprint of the MDP an agent trains on: its variant, horizon and discount.
    The server refuses an agent whose digest differs from the one it computed for its index."""
    text = f"{variant.digest()}|H={training_horizon(run, variant)}|γ={discount(run, variant)!r}"
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def range_digest(digests: list[str]) -> str:
    """One digest for the variant digests of an agent host's index range (in index order):
    the host sends it once, the server recomputes it from the digests it expects."""
    return hashlib.sha256("|".join(digests).encode()).hexdigest()[:32]
