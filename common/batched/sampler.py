"""Lockstep rollouts of many agents: one env step and one stacked policy forward per time
step for every agent's copies.

Agent a runs ``counts[a]`` copies of its variant for one episode each (at most its horizon),
exactly as the one-agent sampler (common/rollout.py) does, with all randomness from its own
generator: first its env seed, then its action uniforms, drawn ``UNIFORM_CHUNK`` steps at a
time while it still runs. What an agent draws and does therefore depends on it alone.
Agents are laid out grouped by their copy count (each group one stacked forward).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fedhpg.common.batched.maths import NUMPY, PolicyMaths
from fedhpg.envs.multi import MultiBatchEnv

UNIFORM_CHUNK = 32
"""Time steps of action uniforms an agent draws at once."""


@dataclass(frozen=True)
class Rollouts:
    """Every agent's batch, time-major over the longest agent (T steps), copies as blocks.

    Agent a's block is columns ``offsets[a]:offsets[a+1]``; ``lengths[a]`` is its own T_a
    (its batch ends when all its copies ended); ``alive`` is False past each copy's end.
    """

    obs: np.ndarray  # [T, N, obs_dim] float32
    actions: np.ndarray  # [T, N] int64
    rewards: np.ndarray  # [T, N] float64
    alive: np.ndarray  # [T, N] bool
    success: np.ndarray  # [N] bool
    offsets: np.ndarray  # [A + 1]
    lengths: np.ndarray  # [A]

    @property
    def owner(self) -> np.ndarray:
        """The agent (batch position) of every copy, [N]."""
        return np.repeat(np.arange(len(self.lengths)), np.diff(self.offsets))


@dataclass(frozen=True)
class Batches:
    """Several agents' just-ended batches, as the gradient needs them: rewards and alive flags
    padded to [T, W] (agent blocks of copies; for the coefficients), and the alive steps'
    observations and actions agent by agent, each agent's in time-major order."""

    rewards: np.ndarray  # [T, W] float64
    alive: np.ndarray  # [T, W] bool
    offsets: np.ndarray  # [A + 1]
    lengths: np.ndarray  # [A]
    row_agent: np.ndarray  # [R] non-decreasing
    row_cell: np.ndarray  # [R] flat index into [T, W]
    obs: np.ndarray  # [R, obs_dim] float32
    actions: np.ndarray  # [R] int64

    @property
    def owner(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.lengths)), np.diff(self.offsets))

    def env_steps(self) -> np.ndarray:
        """Alive steps per agent, [A]."""
        return np.bincount(self.row_agent, minlength=len(self.lengths))

    @classmethod
    def of(cls, rollouts: Rollouts) -> Batches:
        """The batches of a lockstep rollout."""
        steps, cols = np.nonzero(rollouts.alive)  # time-major
        agent = rollouts.owner[cols]
        order = np.argsort(agent, kind="stable")
        width = rollouts.alive.shape[1]
        return cls(
            rewards=rollouts.rewards,
            alive=rollouts.alive,
            offsets=rollouts.offsets,
            lengths=rollouts.lengths,
            row_agent=agent[order],
            row_cell=(steps * width + cols)[order],
            obs=rollouts.obs[steps, cols][order],
            actions=rollouts.actions[steps, cols][order],
        )


def rollout(
    env: MultiBatchEnv,
    layers: Any,
    rngs: Sequence[np.random.Generator],
    horizons: Sequence[int],
    *,
    greedy: bool = False,
    maths: PolicyMaths = NUMPY,
) -> Rollouts:
    """One episode in every copy of every agent (agents in ``env``'s block order).

    Agents whose copies have all ended drop out of the stepping and the forward: the set of
    stepped agents is narrowed whenever it has shrunk by a quarter (episode lengths vary a
    lot, and a batch lasts as long as its longest episode). ``layers`` come from ``maths``.
    """
    counts = np.asarray(env.counts)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    num_agents, num_envs = len(counts), int(offsets[-1])
    seeds = [int(rng.integers(2**63 - 1)) for rng in rngs]
    obs = env.reset(seeds)
    horizon = int(max(horizons))
    stop_at = np.repeat(np.asarray(horizons), counts)
    obs_buf = np.zeros((horizon, *obs.shape), dtype=np.float32)
    act_buf = np.zeros((horizon, num_envs), dtype=np.int64)
    rewards = np.zeros((horizon, num_envs), dtype=np.float64)
    alive = np.zeros((horizon, num_envs), dtype=bool)
    success = np.zeros(num_envs, dtype=bool)
    running = np.ones(num_envs, dtype=bool)
    agent_running = np.ones(num_agents, dtype=bool)
    lengths = np.zeros(num_agents, dtype=np.int64)
    uniforms = np.zeros((UNIFORM_CHUNK, num_envs))
    plan = _Plan(np.arange(num_agents), counts, offsets, layers, maths)
    steps = 0
    while steps < horizon and agent_running.any():
        if 4 * int(agent_running.sum()) <= 3 * len(plan.agents):
            plan = _Plan(np.nonzero(agent_running)[0], counts, offsets, layers, maths)
        if not greedy and steps % UNIFORM_CHUNK == 0:
            for a in np.nonzero(agent_running)[0]:
                block = slice(offsets[a], offsets[a + 1])
                uniforms[:, block] = rngs[int(a)].random((UNIFORM_CHUNK, int(counts[a])))
        copies = plan.copies
        live_obs = obs if plan.everyone else obs[copies]
        actions = np.empty(len(copies), dtype=np.int64)
        row = 0
        for group_layers, num, size in plan.groups:
            rows = slice(row, row + num * size)
            draws = None if greedy else uniforms[steps % UNIFORM_CHUNK, copies[rows]]
            actions[rows] = maths.act(group_layers, live_obs[rows].reshape(num, size, -1), draws)
            row += num * size
        obs_buf[steps, copies] = live_obs
        act_buf[steps, copies] = actions
        alive[steps] = running
        lengths += agent_running
        step = env.step(actions, None if plan.everyone else plan.agents)
        live_running = running[copies]
        rewards[steps, copies] = step.reward * live_running
        success[copies] |= live_running & step.success
        running[copies] = live_running & ~(step.terminated | step.truncated)
        steps += 1
        running &= stop_at > steps
        agent_running = np.logical_or.reduceat(running, offsets[:-1])
        if plan.everyone:
            obs = step.obs
        else:
            obs[copies] = step.obs
    return Rollouts(
        obs=obs_buf[:steps],
        actions=act_buf[:steps],
        rewards=rewards[:steps],
        alive=alive[:steps],
        success=success,
        offsets=offsets,
        lengths=lengths,
    )


class _Plan:
    """The agents a rollout still steps: their copies, and one stacked forward per run of
    agents with equal copy counts (with those agents' layers)."""

    def __init__(
        self,
        agents: np.ndarray,
        counts: np.ndarray,
        offsets: np.ndarray,
        layers: Any,
        maths: PolicyMaths,
    ) -> None:
        self.agents = agents
        self.everyone = len(agents) == len(counts)
        self.copies = (
            np.arange(int(offsets[-1]))
            if self.everyone
            else np.concatenate([np.arange(offsets[a], offsets[a + 1]) for a in agents])
        )
        self.groups: list[tuple[Any, int, int]] = []
        for start, end, size in _groups(counts[agents]):
            chosen = agents[start:end]
            self.groups.append((maths.select(layers, chosen), end - start, size))


def _groups(counts: np.ndarray) -> list[tuple[int, int, int]]:
    """(first agent, end agent, copies) of each run of equal copy counts."""
    groups, start = [], 0
    for a in range(1, len(counts) + 1):
        if a == len(counts) or counts[a] != counts[start]:
            groups.append((start, a, int(counts[start])))
            start = a
    return groups


def block_order(indices: Sequence[int], counts: dict[int, int]) -> list[int]:
    """The agents in the order a rollout lays them out: by copy count, then index."""
    return sorted(indices, key=lambda k: (counts[k], k))
