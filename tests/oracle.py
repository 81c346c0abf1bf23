"""The per-agent reference path, kept for tests: one agent's batch sampled step by step and
its gradient by autograd (``common/learning/estimators.py``'s ``estimate_gradient``).

The engine (``common/learning/engine``) is what runs; this is what it is checked against: a plain
loop over time steps for B copies of one environment, the policy's own ``act`` with uniforms
from a numpy ``Generator``, and one autograd pass over the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.learning.bounds import bound_stats, gradient_moments
from fedhpg.common.learning.estimators import (
    estimate_gradient,
    estimator_coefficients,
    per_trajectory_gradients,
)
from fedhpg.common.learning.policies import Policy
from fedhpg.envs.base import BatchEnv


@dataclass(frozen=True, kw_only=True)
class TrajectoryBatch:
    """B trajectories, time-major, padded to the longest one (T ≤ H steps)."""

    obs: np.ndarray  # [T, B, *obs_shape]
    actions: np.ndarray  # [T, B, *act_shape]
    log_probs: np.ndarray  # [T, B] float64, log π(a_t|s_t) (0 when greedy or dead)
    rewards: np.ndarray  # [T, B] float64
    alive: np.ndarray  # [T, B] bool
    success: np.ndarray  # [B] bool

    @property
    def num_trajectories(self) -> int:
        return int(self.alive.shape[1])

    @property
    def num_steps(self) -> int:
        return int(self.alive.sum())

    @property
    def lengths(self) -> np.ndarray:
        return self.alive.sum(axis=0)

    def returns(self, gamma: float = 1.0) -> np.ndarray:
        discounts = gamma ** np.arange(self.rewards.shape[0], dtype=np.float64)
        return discounts @ self.rewards


def sample_trajectories(
    env: BatchEnv,
    policy: Policy,
    rng: np.random.Generator,
    *,
    horizon: int,
    greedy: bool = False,
) -> TrajectoryBatch:
    """One episode (at most ``horizon`` steps) in each of the ``env.num_envs`` copies, every
    random number from ``rng`` (the environment's seed, then each decision's uniforms)."""
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    num_envs = env.num_envs
    obs = env.reset(seed=int(rng.integers(2**63 - 1)))
    obs_buf = np.zeros((horizon, *np.asarray(obs).shape), dtype=np.asarray(obs).dtype)
    rewards = np.zeros((horizon, num_envs), dtype=np.float64)
    alive = np.zeros((horizon, num_envs), dtype=bool)
    success = np.zeros(num_envs, dtype=bool)
    running = np.ones(num_envs, dtype=bool)
    act_buf: np.ndarray | None = None
    steps = 0
    with torch.no_grad():
        while steps < horizon:
            noise = None if greedy else torch.from_numpy(rng.random((num_envs, policy.noise_size)))
            chosen = policy.act(torch.as_tensor(obs), None if noise is None else noise.float())
            actions = chosen.numpy()
            if act_buf is None:
                act_buf = np.zeros((horizon, *actions.shape), dtype=actions.dtype)
            obs_buf[steps] = obs
            act_buf[steps] = actions
            alive[steps] = running
            step = env.step(actions)
            rewards[steps] = step.reward * running
            success |= running & step.success
            running &= ~(step.terminated | step.truncated)
            obs = step.obs
            steps += 1
            if not running.any():
                break
        assert act_buf is not None
        obs_buf, act_buf, alive = obs_buf[:steps], act_buf[:steps], alive[:steps]
        log_probs = np.zeros(alive.shape)
        if not greedy:
            values = policy.log_prob(torch.from_numpy(obs_buf), torch.from_numpy(act_buf))
            log_probs = np.where(alive, values.double().numpy(), 0.0)
    return TrajectoryBatch(obs=obs_buf, actions=act_buf, log_probs=log_probs,
                           rewards=rewards[:steps], alive=alive, success=success)  # fmt: skip


def batch_gradient(
    policy: Policy,
    batch: TrajectoryBatch,
    *,
    algo: AlgoConfig,
    gamma: float,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """(1/B) Σ_b g(τ_b | θ) with the configured estimator and baseline, by autograd."""
    coefficients = _coefficients(batch, algo, gamma, weights)
    obs, actions = torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)
    return estimate_gradient(policy, obs, actions, coefficients)


def bound_statistics(
    policy: Policy, batch: TrajectoryBatch, *, algo: AlgoConfig, gamma: float
) -> dict[str, float]:
    """Theorem 1's constants from the batch's per-trajectory gradients (autograd, vmap)."""
    if batch.num_trajectories < 2:
        return {}
    coefficients = _coefficients(batch, algo, gamma)
    obs, actions = torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)
    rows = per_trajectory_gradients(policy, obs, actions, coefficients)
    return bound_stats(gradient_moments(rows))


def _coefficients(
    batch: TrajectoryBatch, algo: AlgoConfig, gamma: float, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """The configured estimator's coefficients of one agent's batch, [T, B]."""
    return estimator_coefficients(
        algo.estimator,  # type: ignore[arg-type]
        torch.from_numpy(batch.rewards),
        torch.from_numpy(batch.alive),
        gamma=gamma,
        baseline=algo.baseline,  # type: ignore[arg-type]
        weights=weights,
        reward_to_go=algo.reward_to_go,  # type: ignore[arg-type]
        normalize=algo.normalize,  # type: ignore[arg-type]
    )
