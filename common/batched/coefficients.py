"""REINFORCE (eq. 5) and GPOMDP (eq. 6) coefficients of many agents' batches at once.

The maths of common/estimators.py, on a [T, N] layout of copies in agent blocks: per-step
discounts from each copy's own γ, the leave-one-out mean baseline over the copies *of the same
agent*, reward-to-go along time. Agent-independence: sums over an agent's copies are
``np.add.reduceat`` over its own block (each block reduced on its own), sums along time are
sequential (``cumsum``), so zero rows past an agent's own end (another agent ran longer) add
exact zeros.

The practice options of common/estimators.py (``reward_to_go="from_step"``, ``normalize``;
departures from eq. 5/6, biased) are here too, agent by agent in the same way: the backward
recursion R_t = x_t + γ R_{t+1} with each copy's own γ, and means and spreads over one agent's
block of copies (``"batch"``) or one copy (``"episode"``).
"""

from __future__ import annotations

import itertools

import numpy as np

from fedhpg.common.batched.sampler import Batches, Rollouts
from fedhpg.common.estimators import NORMALIZE_EPS


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
    rollouts: Rollouts | Batches,
    gammas: np.ndarray,
    *,
    estimator: str,
    baseline: str,
    reward_to_go: str = "from_start",
    normalize: str = "none",
) -> np.ndarray:
    """coef[t, copy] per the estimator (float64, 0 on dead steps); ``gammas`` per agent."""
    return _normalized(
        _raw_coefficients(rollouts, gammas, estimator, baseline, reward_to_go),
        rollouts,
        normalize,
    )


def _raw_coefficients(
    rollouts: Rollouts | Batches,
    gammas: np.ndarray,
    estimator: str,
    baseline: str,
    reward_to_go: str,
) -> np.ndarray:
    steps = rollouts.rewards.shape[0]
    gamma = gammas[rollouts.owner]
    if estimator == "gpomdp" and reward_to_go == "from_step":
        values = rollouts.rewards
        if baseline == "mean":
            values = values - _leave_one_out(values, rollouts)
        tail = np.empty_like(values)
        running = np.zeros(values.shape[1])
        for t in range(steps - 1, -1, -1):
            running = values[t] + gamma * running
            tail[t] = running
        return rollouts.alive * tail
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
        tail_sums = np.cumsum(step_rewards[::-1], axis=0)[::-1]
        return rollouts.alive * tail_sums
    raise ValueError(f"estimator must be 'reinforce' or 'gpomdp', got {estimator!r}")


def _normalized(coef: np.ndarray, rollouts: Rollouts | Batches, normalize: str) -> np.ndarray:
    """(c − mean)/(std + ε) over each agent's alive cells ('batch') or each copy's ('episode').

    Sums along time first, sequentially (the rows past an agent's end add exact zeros), then
    over the agent's own columns: no sum's grouping depends on the other agents' lengths."""
    if normalize == "none":
        return coef
    if normalize == "episode":
        starts = np.arange(coef.shape[1] + 1)  # every copy its own block
    elif normalize == "batch":
        starts = np.asarray(rollouts.offsets)
    else:
        raise ValueError(f"normalize must be 'none', 'batch' or 'episode', got {normalize!r}")
    mask = rollouts.alive.astype(np.float64)

    def block_totals(values: np.ndarray) -> np.ndarray:
        per_copy = np.cumsum(values, axis=0)[-1] if values.shape[0] else np.zeros(values.shape[1])
        return np.array([per_copy[low:high].sum() for low, high in itertools.pairwise(starts)])

    counts = np.diff(starts)
    count = np.maximum(block_totals(mask), 1.0)
    mean = np.repeat(block_totals(coef * mask) / count, counts)
    spread = np.repeat(block_totals((coef - mean) ** 2 * mask) / count, counts)
    return mask * (coef - mean) / (np.sqrt(spread) + NORMALIZE_EPS)


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
