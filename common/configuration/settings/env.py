"""The ``env`` section: which environment family, its level, seed, horizon and γ."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.settings.checks import check_int, check_number, require

GYM_FAMILY = "gym"
"""The family of any registered gymnasium id (``env.id``), varied by ``env.vary``."""


@dataclass(kw_only=True)
class EnvConfig:
    """Which environment family, and how its K variants differ."""

    family: str = "gridworld"
    """Environment family (see ``fedhpg.envs.registry.FAMILIES``)."""
    level: float = 0.5
    """Heterogeneity level in [0, 1]: 0 = identical variants, 1 = most different."""
    seed: int | None = None
    """Seed of the variant generator; None uses the run seed."""
    horizon: int | None = None
    """Trajectory horizon H; None uses the family's episode step limit."""
    gamma: float | None = None
    """One discount for every agent; None keeps each variant's own γ_k."""
    options: dict[str, Any] = field(default_factory=dict)
    """Family-specific generator options (e.g. GridWorld ``size``, ``vary_goal``)."""
    id: str | None = None
    """``env.family=gym`` (``env=gym``): the registered gymnasium id every agent runs, e.g.
    MountainCar-v0."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """``env=gym``: constructor keywords of every agent's environment (``gym.make(id,
    **kwargs)``)."""
    vary: dict[str, Any] = field(default_factory=dict)
    """``env=gym``: what differs between agents, name → a seeded distribution ({choice: [...]},
    {uniform: {low, high}}, {lognormal: {median, sigma}}) or {spread: s} (the environment's own
    value × (1 + s·level·u), u ~ U(−1, 1)); a constructor keyword, an attribute of the
    unwrapped environment, or ``gamma`` (the agent's discount)."""


def validate_env(env: EnvConfig) -> None:
    check_number(env.level, "env.level", low=0.0)
    require(env.level <= 1.0, "env.level", f"got {env.level!r}, must be in [0, 1]")
    if env.seed is not None:
        check_int(env.seed, "env.seed", low=0)
    if env.horizon is not None:
        check_int(env.horizon, "env.horizon", low=1)
    if env.gamma is not None:
        check_number(env.gamma, "env.gamma", low=0.0, low_open=True)
        require(env.gamma <= 1.0, "env.gamma", f"got {env.gamma!r}, must be in (0, 1]")
    if env.family != GYM_FAMILY:
        for key in ("id", "kwargs", "vary"):
            require(
                not getattr(env, key),
                f"env.{key}",
                f"is read by env=gym (env.family=gym) only, not env.family={env.family}",
            )
