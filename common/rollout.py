"""The rollout sampler: B trajectories of horizon H from a batched environment.

One batched policy call per time step serves all B copies. Steps taken after a copy's episode
ended are masked: they are neither counted nor part of any return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fedhpg.common.policies import ActionSampler, Policy
from fedhpg.envs.base import BatchEnv


@dataclass(frozen=True, kw_only=True)
class TrajectoryBatch:
    """B trajectories, time-major, padded to the longest one (T ≤ H steps).

    ``alive[t, b]`` is True when step t of trajectory b happened; everything at a dead step
    (observation, action, reward, log-probability) is padding with reward 0.
    """

    obs: np.ndarray  # [T, B, *obs_shape]
    actions: np.ndarray  # [T, B, *act_shape]
    log_probs: np.ndarray  # [T, B] float64, log π(a_t|s_t) of the sampling policy (0 if greedy)
    rewards: np.ndarray  # [T, B] float64
    alive: np.ndarray  # [T, B] bool
    success: np.ndarray  # [B] bool

    @property
    def num_trajectories(self) -> int:
        return int(self.alive.shape[1])

    @property
    def num_steps(self) -> int:
        """Environment steps that count: the alive ones."""
        return int(self.alive.sum())

    @property
    def lengths(self) -> np.ndarray:
        return self.alive.sum(axis=0)

    def returns(self, gamma: float = 1.0) -> np.ndarray:
        """Per-trajectory return Σ_h γ^h r_h, shape [B]."""
        discounts = gamma ** np.arange(self.rewards.shape[0], dtype=np.float64)
        return discounts @ self.rewards


def sample_trajectories(
    env: BatchEnv,
    policy: Policy,
    rng: np.random.Generator,
    *,
    horizon: int,
    greedy: bool = False,
    sampler: ActionSampler | None = None,
) -> TrajectoryBatch:
    """Run one episode (at most ``horizon`` steps) in each of the ``env.num_envs`` copies.

    All randomness comes from ``rng``: the environment's seed and the policy's action noise.
    ``sampler`` replaces the policy's own action sampler (a Byzantine agent's random actions);
    log-probabilities are always the sampler's.
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    num_envs = env.num_envs
    act = sampler if sampler is not None else policy.sampler()
    obs = env.reset(seed=int(rng.integers(2**63 - 1)))
    obs_buf = np.zeros((horizon, *obs.shape), dtype=obs.dtype)
    rewards = np.zeros((horizon, num_envs), dtype=np.float64)
    alive = np.zeros((horizon, num_envs), dtype=bool)
    success = np.zeros(num_envs, dtype=bool)
    running = np.ones(num_envs, dtype=bool)
    ended = np.empty(num_envs, dtype=bool)
    act_buf: np.ndarray | None = None

    steps = 0
    while steps < horizon:
        actions = act(obs, rng, greedy)
        if act_buf is None:
            act_buf = np.zeros((horizon, *actions.shape), dtype=actions.dtype)
        obs_buf[steps] = obs
        # The raw sample is recorded and its log-probability taken, not the clipped action the
        # env receives (Box actions are clipped to the bounds inside the batch env): the
        # gradient is that of log π at the sample the policy drew.
        act_buf[steps] = actions
        alive[steps] = running
        step = env.step(actions)
        np.multiply(step.reward, running, out=rewards[steps])
        success |= running & step.success
        np.logical_or(step.terminated, step.truncated, out=ended)
        running &= ~ended
        obs = step.obs
        steps += 1
        if not running.any():
            break

    assert act_buf is not None
    obs_buf, act_buf, alive = obs_buf[:steps], act_buf[:steps], alive[:steps]
    return TrajectoryBatch(
        obs=obs_buf,
        actions=act_buf,
        log_probs=np.zeros(alive.shape) if greedy else _log_probs(act, obs_buf, act_buf, alive),
        rewards=rewards[:steps],
        alive=alive,
        success=success,
    )


def _log_probs(
    sampler: ActionSampler, obs: np.ndarray, actions: np.ndarray, alive: np.ndarray
) -> np.ndarray:
    """log π(a_t|s_t) on the alive steps of the whole batch in one call (0 on dead steps)."""
    values = np.zeros(alive.shape, dtype=np.float64)
    values[alive] = sampler.log_prob(obs[alive], actions[alive])
    return values
