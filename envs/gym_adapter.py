""":class:`BatchEnv` s over registered gymnasium environments: a vector env when the env has a
numpy-vectorised implementation, otherwise B plain copies stepped only while they run."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchStep
from fedhpg.envs.spaces import is_flattened, policy_observation_space


class ActionBounds:
    """Clips continuous actions to a Box action space's bounds.

    A Gaussian policy's sample is unbounded. Some environments clip it themselves (Pendulum,
    LunarLander), others pass it to the simulator's own clamp (MuJoCo's ``ctrlrange``) and
    still charge their action cost on the raw value, as does our per-variant action cost:
    an unclipped sample of 10⁴ then costs 10⁸ per step and the returns blow up. Clipping here,
    before the env and before any action cost, makes every family see only valid actions.
    Discrete spaces pass through unchanged.
    """

    def __init__(self, space: gym.Space) -> None:
        self._low: np.ndarray | None = None
        self._high: np.ndarray | None = None
        if isinstance(space, gym.spaces.Box):
            self._low, self._high = np.asarray(space.low), np.asarray(space.high)

    def __call__(self, actions: np.ndarray) -> np.ndarray:
        if self._low is None:
            return actions
        return np.clip(actions, self._low, self._high)


class GymVectorBatchEnv:
    """B copies of a registered gymnasium env, stepped as one vector env.

    Uses the env's own numpy-vectorised implementation when it has one (CartPole does) and
    ``SyncVectorEnv`` otherwise (:class:`GymLoopBatchEnv` is faster there; this path stays for
    comparison). Copies whose episode ended are auto-reset by gymnasium; the sampler masks
    those steps, so no bookkeeping is needed here. Observations a policy does not take as
    they are (Dict, Tuple, ...) are flattened (:mod:`fedhpg.envs.spaces`).
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        env_kwargs: dict[str, Any] | None = None,
        configure: Callable[[Any], None] | None = None,
        action_cost: float = 0.0,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        kwargs = dict(env_kwargs or {})
        spec = gym.spec(env_id)
        mode = "vector_entry_point" if spec.vector_entry_point is not None else "sync"
        self._env = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=mode, **kwargs)
        if is_flattened(self._env.single_observation_space):
            self._env = gym.wrappers.vector.FlattenObservation(self._env)
        if configure is not None:
            self._configure(configure)
        self.action_cost = action_cost
        self.num_envs = num_envs
        self._no_success = np.zeros(num_envs, dtype=bool)
        self.single_observation_space = self._env.single_observation_space
        self.single_action_space = self._env.single_action_space
        self._bound = ActionBounds(self.single_action_space)

    def _configure(self, configure: Callable[[Any], None]) -> None:
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
        actions = self._bound(actions)
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


class GymLoopBatchEnv:
    """B plain copies of a registered gymnasium env, stepped one by one while their episode runs.

    For envs without a numpy-vectorised implementation. Unlike ``SyncVectorEnv`` it steps only
    the copies whose episode is still running (the :class:`BatchEnv` protocol allows freezing
    the others), never auto-resets a finished copy, steps the unwrapped envs (no checker or
    order-enforcing wrappers on the hot path) and merges no ``info`` dicts. Episode lengths of
    e.g. LunarLander range from ~70 to 1000 steps, so skipping finished copies saves most of
    the work. Copy i is reset with ``seed + i``, as ``SyncVectorEnv`` does, so both produce the
    same steps for the running copies; ``step_limit`` (default: the registered one) truncates
    episodes. Observations a policy does not take as they are (Dict, Tuple, ...) are
    flattened (:mod:`fedhpg.envs.spaces`).
    A frozen copy repeats its last observation with reward 0 and its final flags.
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        env_kwargs: dict[str, Any] | None = None,
        configure: Callable[[Any], None] | None = None,
        action_cost: float = 0.0,
        step_limit: int = 0,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        kwargs = dict(env_kwargs or {})
        self._envs: list[gym.Env] = [gym.make(env_id, **kwargs).unwrapped for _ in range(num_envs)]
        if configure is not None:
            for env in self._envs:
                configure(env)
        limit = step_limit or gym.spec(env_id).max_episode_steps
        self._limit = int(limit) if limit is not None else None
        self.action_cost = action_cost
        self.num_envs = num_envs
        raw_space = self._envs[0].observation_space
        self._flattened_from = raw_space if is_flattened(raw_space) else None
        self.single_observation_space = policy_observation_space(raw_space)
        self.single_action_space = self._envs[0].action_space
        self._bound = ActionBounds(self.single_action_space)
        shape, dtype = self.single_observation_space.shape, self.single_observation_space.dtype
        self._obs = np.zeros((num_envs, *(shape or ())), dtype=dtype)
        self._running = np.zeros(num_envs, dtype=bool)
        self._terminated = np.zeros(num_envs, dtype=bool)
        self._truncated = np.zeros(num_envs, dtype=bool)
        self._steps = np.zeros(num_envs, dtype=np.int64)

    def reset(self, *, seed: int) -> np.ndarray:
        for i, env in enumerate(self._envs):
            obs, _ = env.reset(seed=seed + i)
            self._obs[i] = self._observed(obs)
        self._running[:] = True
        self._terminated[:] = False
        self._truncated[:] = False
        self._steps[:] = 0
        return self._obs.copy()

    def _observed(self, obs: Any) -> Any:
        if self._flattened_from is None:
            return obs
        return gym.spaces.flatten(self._flattened_from, obs)

    def step(self, actions: np.ndarray) -> BatchStep:
        actions = self._bound(actions)
        reward = np.zeros(self.num_envs, dtype=np.float64)
        success = np.zeros(self.num_envs, dtype=bool)
        running = np.flatnonzero(self._running)
        for i in running:
            obs, r, terminated, truncated, info = self._envs[i].step(actions[i])
            self._obs[i] = self._observed(obs)
            reward[i] = r
            self._steps[i] += 1
            if self._limit is not None and self._steps[i] >= self._limit:
                truncated = True
            if terminated or truncated:
                self._running[i] = False
                self._terminated[i] = terminated
                self._truncated[i] = truncated
            if info and info.get("is_success"):
                success[i] = True
        if self.action_cost and running.size:
            flat = np.square(actions[running]).reshape(running.size, -1).sum(1)
            reward[running] -= self.action_cost * flat
        return BatchStep(
            obs=self._obs.copy(),
            reward=reward,
            terminated=self._terminated.copy(),
            truncated=self._truncated.copy(),
            success=success,
        )

    def close(self) -> None:
        for env in self._envs:
            env.close()
