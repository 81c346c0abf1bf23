"""A run's K environment variants, and the settings each agent derives from its own."""

from __future__ import annotations

import hashlib

from fedhpg.common.config import RunConfig
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.registry import make_variants


def run_variants(run: RunConfig) -> list[EnvVariant]:
    """The K environment variants of a run (deterministic in env.* and the seed)."""
    env = run.env
    return make_variants(
        env.family,
        seed=run.seed if env.seed is None else env.seed,
        num_agents=run.agents.num_agents,
        level=env.level,
        **env.options,
    )


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
