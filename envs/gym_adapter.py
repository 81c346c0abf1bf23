"""A :class:`BatchEnv` over any gymnasium vector environment."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchStep


class GymVectorBatchEnv:
    """B copies of a registered gymnasium env, stepped as one vector env.

    Uses the env's own numpy-vectorised implementation when it has one (CartPole does) and
    ``SyncVectorEnv`` otherwise. Copies whose episode ended are auto-reset by gymnasium; the
    sampler masks those steps, so no bookkeeping is needed here.
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        env_kwargs: dict[str, Any] | None = None,
        configure: Callable[[gym.Env], None] | None = None,
        action_cost: float = 0.0,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        kwargs = dict(env_kwargs or {})
        spec = gym.spec(env_id)
        mode = "vector_entry_point" if spec.vector_entry_point is not None else "sync"
        self._env = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=mode, **kwargs)
        if configure is not None:
            self._configure(configure)
        self.action_cost = action_cost
        self.num_envs = num_envs
        self._no_success = np.zeros(num_envs, dtype=bool)
        self.single_observation_space = self._env.single_observation_space
        self.single_action_space = self._env.single_action_space

    def _configure(self, configure: Callable[[gym.Env], None]) -> None:
        """Apply a variant's physics to every copy (a vector-native env holds it once)."""
        base = self._env.unwrapped
        if isinstance(base, gym.vector.SyncVectorEnv):
            for env in base.envs:
                configure(env.unwrapped)
        else:
            configure(base)

    def reset(self, *, seed: int) -> np.ndarray:
        obs, _ = self._env.reset(seed=seed)
        return obs

    def step(self, actions: np.ndarray) -> BatchStep:
        obs, reward, terminated, truncated, info = self._env.step(actions)
        if self.action_cost:
            reward = reward - self.action_cost * np.square(actions).reshape(self.num_envs, -1).sum(
                1
            )
        success = info.get("is_success")
        return BatchStep(
            obs=obs,
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            success=self._no_success if success is None else np.asarray(success, dtype=bool),
        )

    def close(self) -> None:
        self._env.close()
