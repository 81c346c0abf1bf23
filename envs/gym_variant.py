"""Environment variants backed by a registered gymnasium environment."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym

from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.gym_adapter import GymVectorBatchEnv


@dataclass(frozen=True, kw_only=True)
class GymVariant(EnvVariant):
    """A gymnasium env id, constructor kwargs, and physics attributes set after construction."""

    env_id: str
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    attributes: dict[str, Any] = field(default_factory=dict)
    step_limit: int = 0
    """Episode step limit; 0 uses the registered ``max_episode_steps``."""

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        env = gym.make(self.env_id, render_mode=render_mode, **self.env_kwargs)
        for name, value in self.attributes.items():
            setattr(env.unwrapped, name, value)
        return env

    def make_batch_env(self, num_envs: int) -> BatchEnv:
        return GymVectorBatchEnv(
            self.env_id, num_envs, env_kwargs=self.env_kwargs, attributes=self.attributes
        )

    @property
    def max_episode_steps(self) -> int:
        if self.step_limit:
            return self.step_limit
        limit = gym.spec(self.env_id).max_episode_steps
        if limit is None:
            raise ValueError(f"{self.env_id} has no step limit: set env.horizon")
        return int(limit)
