"""Every environment family as a gymnasium id, so single-agent libraries run the same MDPs.

``gym.make("fedhpg/CartPole-v1", level=0.5, index=2, num_agents=4, seed=0)`` is agent 2's
variant of a 4-agent CartPole federation at level 0.5 whose variant seed is 0 (``env.seed``, or
the run seed when that is unset): the variant parameters, and so the observations and rewards
for the same reset seed and actions, are those the federation's agent 2 trains on. Family
options (``env.options``) pass through as further keywords.

The ids are registered when :mod:`fedhpg.envs` is imported. gymnasium 1.x loads no plugins by
itself, but its ``"module:id"`` form imports the module first:
``gym.make("fedhpg.envs:fedhpg/CartPole-v1", ...)`` works in a process that never imported
fedhpg.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from fedhpg.envs.registry import make_variant

GYM_IDS: dict[str, str] = {
    "gridworld": "fedhpg/GridWorldVariant-v0",
    "cartpole": "fedhpg/CartPole-v1",
    "acrobot": "fedhpg/Acrobot-v1",
    "pendulum": "fedhpg/Pendulum-v1",
    "mountaincar": "fedhpg/MountainCar-v0",
    "lunarlander": "fedhpg/LunarLander-v3",
    "lunarlander-continuous": "fedhpg/LunarLanderContinuous-v3",
    "halfcheetah": "fedhpg/HalfCheetah-v5",
}
"""Family name → gymnasium id. (``fedhpg/GridWorld-v0`` is the plain GridWorld of a given
layout; ``fedhpg/GridWorldVariant-v0`` is one agent's generated variant.)"""

DEFAULT_NUM_AGENTS = 4


def make_variant_env(
    *,
    family: str,
    level: float = 0.5,
    index: int = 0,
    num_agents: int = DEFAULT_NUM_AGENTS,
    seed: int = 0,
    render_mode: str | None = None,
    **options: Any,
) -> gym.Env:
    """Agent ``index``'s variant of ``family``, as one gymnasium env."""
    if not 0 <= index < num_agents:
        raise ValueError(f"index must be in [0, num_agents={num_agents}), got {index!r}")
    variant = make_variant(family, index, seed=seed, num_agents=num_agents, level=level, **options)
    return variant.make_env(render_mode=render_mode)


def register_gym_ids() -> None:
    """Register every id of :data:`GYM_IDS` once (the package import and users may both call)."""
    for family, env_id in GYM_IDS.items():
        if env_id in gym.registry:
            continue
        # The variant's own env carries its step limit (a TimeLimit inside); no second one.
        gym.register(
            id=env_id,
            entry_point="fedhpg.envs.gym_ids:make_variant_env",
            kwargs={"family": family},
            disable_env_checker=True,
        )
