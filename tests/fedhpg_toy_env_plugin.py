"""A plugin outside the package: an environment family and a policy, as a user would write
them. Named by registered name (``plugins=[fedhpg_toy_env_plugin] env.family=short_cartpoles
policy.name=linear_softmax``) or by dotted path (``env.family=fedhpg_toy_env_plugin:
short_cartpoles policy.name=fedhpg_toy_env_plugin:LinearSoftmaxPolicy``, no plugins needed).

- ``short_cartpoles``: K CartPole variants whose pole half-length is 0.5 ± 0.3·level, with
  episodes cut at 60 steps and γ = 0.95; each reports its ``toy_length``.
- ``linear_softmax``: π(a|s) = softmax(W s + b), no hidden layer (10 parameters on CartPole).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from fedhpg.common.configuration.settings.policy import PolicyConfig
from fedhpg.common.learning.policies import Policy, register_policy
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.registry import register_family

STEP_LIMIT = 60


@register_family("short_cartpoles")
def short_cartpoles(
    *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    if options:
        raise ValueError(f"short_cartpoles takes no options, got {sorted(options)}")
    draws = np.random.default_rng([seed, 0x70]).uniform(-1.0, 1.0, size=num_agents)
    variants: list[EnvVariant] = []
    for k, u in enumerate(draws):
        length = float(0.5 + 0.3 * level * u)
        variants.append(
            GymVariant(
                family="short_cartpoles",
                index=k,
                gamma=0.95,
                params={"toy_length": round(length, 6)},
                env_id="CartPole-v1",
                attributes={"length": length, "polemass_length": 0.1 * length},
                step_limit=STEP_LIMIT,
            )
        )
    return variants


class _MissingLibraryVariant(GymVariant):
    """A variant whose simulator is not installed, as MuJoCo or Box2D are without the extra."""

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        raise gym.error.DependencyNotInstalled("FooSim is not installed, run `pip install foosim`")


def needs_a_missing_library(
    *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    """``env.family=fedhpg_toy_env_plugin:needs_a_missing_library``: must fail in one line."""
    return [
        _MissingLibraryVariant(
            family="needs_a_missing_library", index=k, gamma=0.99, params={}, env_id="CartPole-v1"
        )
        for k in range(num_agents)
    ]


@register_policy("linear_softmax")
class LinearSoftmaxPolicy(Policy):
    """Discrete actions from a 1-D Box observation through one linear layer."""

    def __init__(
        self, observation_space: gym.Space, action_space: gym.Space, config: PolicyConfig
    ) -> None:
        super().__init__()
        assert isinstance(observation_space, gym.spaces.Box)
        assert isinstance(action_space, gym.spaces.Discrete)
        self.linear = nn.Linear(int(observation_space.shape[0]), int(action_space.n))

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        log_pi = torch.log_softmax(self.linear(obs.float()), dim=-1)
        return log_pi.gather(-1, act.long().unsqueeze(-1)).squeeze(-1)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """Its own draw by inverting the CDF (the engine vmaps it over agents: this policy
        does not say ``rows_batched``)."""
        logits = self.linear(obs.float())
        if noise is None:
            return logits.argmax(dim=-1)
        cumulative = torch.softmax(logits, dim=-1).cumsum(dim=-1)
        return (noise[..., :1] * cumulative[..., -1:] > cumulative[..., :-1]).sum(dim=-1)


def not_a_policy(observation_space: gym.Space, action_space: gym.Space, _: PolicyConfig) -> Any:
    """A factory that breaks the contract: an nn.Module, but no Policy."""
    return nn.Linear(4, 2)
