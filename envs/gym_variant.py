"""Environment variants backed by a registered gymnasium environment."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.gym_adapter import ActionBounds, GymLoopBatchEnv, GymVectorBatchEnv
from fedhpg.envs.spaces import is_flattened, policy_observation_space


@dataclass(frozen=True, kw_only=True)
class GymVariant(EnvVariant):
    """A gymnasium env id plus what makes this agent's copy different.

    ``env_kwargs`` go to the constructor; ``attributes`` are set on the unwrapped env after
    construction (classic-control physics); ``mujoco_scales`` multiply MuJoCo model arrays
    (``gravity``, ``friction``, ``mass``); ``action_cost`` subtracts c·‖a‖² from every reward
    (reward heterogeneity for continuous control).
    """

    env_id: str
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    attributes: dict[str, Any] = field(default_factory=dict)
    mujoco_scales: dict[str, float] = field(default_factory=dict)
    action_cost: float = 0.0
    mujoco_total_mass: float = 0.0
    step_limit: int = 0
    """Episode step limit; 0 uses the registered ``max_episode_steps``."""

    def configure(self, env: gym.Env) -> None:
        """Apply this variant's physics to one unwrapped env (or a vector-native env)."""
        for name, value in self.attributes.items():
            setattr(env, name, value)
        if self.mujoco_total_mass > 0:
            import mujoco

            model, data = env.model, env.data  # type: ignore[attr-defined]
            mujoco.mj_setTotalmass(model, self.mujoco_total_mass)
            mujoco.mj_setConst(model, data)
        if self.mujoco_scales:
            model = env.model  # type: ignore[attr-defined]
            model.opt.gravity[:] = model.opt.gravity * self.mujoco_scales.get("gravity", 1.0)
            model.geom_friction[:] = model.geom_friction * self.mujoco_scales.get("friction", 1.0)
            model.body_mass[:] = model.body_mass * self.mujoco_scales.get("mass", 1.0)

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        """One copy of this agent's environment: observations a policy does not take as they
        are (Dict, Tuple, ...) flattened, Box actions clipped to their bounds."""
        env = gym.make(
            self.env_id,
            max_episode_steps=self.step_limit or None,
            render_mode=render_mode,
            **self.env_kwargs,
        )
        self.configure(env.unwrapped)
        if is_flattened(env.observation_space):
            policy_observation_space(env.observation_space)  # one that cannot is refused here
            env = gym.wrappers.FlattenObservation(env)
        if isinstance(env.action_space, gym.spaces.Box) or self.action_cost:
            return _ClippedActions(env, self.action_cost)
        return env

    def make_batch_env(self, num_envs: int) -> BatchEnv:
        """The env's own vectorised implementation if it has one (CartPole) and the registered
        step limit holds, else B plain copies that are stepped only while their episode runs."""
        if gym.spec(self.env_id).vector_entry_point is not None and not self.step_limit:
            return GymVectorBatchEnv(
                self.env_id,
                num_envs,
                env_kwargs=self.env_kwargs,
                configure=self.configure,
                action_cost=self.action_cost,
            )
        return GymLoopBatchEnv(
            self.env_id,
            num_envs,
            env_kwargs=self.env_kwargs,
            configure=self.configure,
            action_cost=self.action_cost,
            step_limit=self.step_limit,
        )

    @property
    def max_episode_steps(self) -> int:
        if self.step_limit:
            return self.step_limit
        limit = gym.spec(self.env_id).max_episode_steps
        if limit is None:
            raise ValueError(f"{self.env_id} has no step limit: set env.horizon=<steps>")
        return int(limit)


class _ClippedActions(gym.Wrapper):
    """The action clipped to the space's bounds (as the batch envs do), then reward − c·‖a‖²."""

    def __init__(self, env: gym.Env, cost: float) -> None:
        super().__init__(env)
        self.cost = cost
        self._bound = ActionBounds(env.action_space)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if isinstance(self.action_space, gym.spaces.Box):
            action = self._bound(np.asarray(action, dtype=self.action_space.dtype))
        obs, reward, terminated, truncated, info = self.env.step(action)
        if not self.cost:
            return obs, float(reward), terminated, truncated, info
        penalty = self.cost * float(np.sum(np.square(action)))
        return obs, float(reward) - penalty, terminated, truncated, info
