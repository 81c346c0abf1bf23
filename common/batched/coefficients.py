"""REINFORCE (eq. 5) and GPOMDP (eq. 6) coefficients of many agents' batches at once.

The maths of common/estimators.py, on a [T, N] layout of copies in agent blocks: per-step
discounts from each copy's own γ, the leave-one-out mean baseline over the copies *of the same
agent*, reward-to-go along time. Agent-independence: sums over an agent's copies are
``np.add.reduceat`` over its own block (each block reduced on its own), sums along time are
sequential (``cumsum``), so zero rows past an agent's own end (another agent ran longer) add
exact zeros.
"""

from __future__ import annotations

import numpy as np

from fedhpg.common.batched.sampler import Batches, Rollouts


def _block_sums(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per time step and agent, the sum over the agent's copies: [T, N] -> [T, A]."""
    return np.add.reduceat(values, offsets[:-1], axis=1)


def _leave_one_out(values: np.ndarray, rollouts: Rollouts | Batches) -> np.ndarray:
    """Each copy's mean over the *other* copies of its agent (0 for an agent of one copy)."""
    counts = np.diff(rollouts.offsets)
    sums = np.repeat(_block_sums(values, rollouts.offsets), counts, axis=1)
    others = np.repeat(np.maximum(counts - 1, 1), counts)
    return (sums - values) / others * np.repeat(counts > 1, counts)


def coefficients(
    rollouts: Rollouts | Batches, gammas: np.ndarray, *, estimator: str, baseline: str
) -> np.ndarray:
    """coef[t, copy] per the estimator (float64, 0 on dead steps); ``gammas`` per agent."""
    steps = rollouts.rewards.shape[0]
    gamma = gammas[rollouts.owner]
    discounts = gamma[None, :] ** np.arange(steps, dtype=np.float64)[:, None]
    step_rewards = discounts * rollouts.rewards
    if estimator == "reinforce":
        returns = np.cumsum(step_rewards, axis=0)[-1:]  # [1, N]
        if baseline == "mean":
            returns = returns - _leave_one_out(returns, rollouts)
        return rollouts.alive * returns
    if estimator == "gpomdp":
        if baseline == "mean":
            step_rewards = step_rewards - _leave_one_out(step_rewards, rollouts)
        reward_to_go = np.cumsum(step_rewards[::-1], axis=0)[::-1]
        return rollouts.alive * reward_to_go
    raise ValueError(f"estimator must be 'reinforce' or 'gpomdp', got {estimator!r}")


def returns(rollouts: Rollouts | Batches, gammas: np.ndarray | None = None) -> np.ndarray:
    """Per copy Σ_t γ^t r_t (undiscounted without ``gammas``), [N]."""
    rewards = rollouts.rewards
    if gammas is not None:
        steps = rewards.shape[0]
        gamma = gammas[rollouts.owner]
        rewards = gamma[None, :] ** np.arange(steps, dtype=np.float64)[:, None] * rewards
    if rewards.shape[0] == 0:
        return np.zeros(rewards.shape[1])
    return np.cumsum(rewards, axis=0)[-1]
