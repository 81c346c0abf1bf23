"""A tiny finite-horizon tabular MDP with an exact objective, for testing the estimators.

Four live states, one absorbing terminal state, two actions, stochastic transitions, a reward
on each transition r(s, a, s') (so the step that ends an episode still pays) and horizon 4.
It is small enough for three independent views of the same distribution over trajectories:

- :func:`exact_objective` — J(θ) by forward recursion over state distributions, in float64
  torch and differentiable in the policy logits, so ∇J(θ) is one ``torch.autograd.grad``;
- :func:`enumerate_trajectories` — every possible trajectory with its exact probability, so
  the *exact* expectation (and variance) of an estimator is a finite weighted sum;
- :class:`TabularMDPBatchEnv` — the same MDP as a numpy :class:`BatchEnv`, stepped by the real
  rollout sampler for the Monte-Carlo tests.

The terminal state is reachable from every live state, so many trajectories end before H and
whole batches of 8 sometimes do too: that exercises the alive masks and the sampler's early
exit. Its own logits are never used at an alive step, so their gradient is exactly zero.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from oracle import TrajectoryBatch, sample_trajectories

from fedhpg.common.learning.policies import TabularSoftmaxPolicy
from fedhpg.envs.base import BatchStep

NUM_STATES = 5  # 0..3 live, 4 terminal (absorbing)
NUM_ACTIONS = 2
TERMINAL = 4
HORIZON = 4

INITIAL = np.array([0.4, 0.3, 0.2, 0.1, 0.0])  # ρ(s_0)

# P[s, a, s']; every live row can end the episode (last column).
TRANSITIONS = np.array(
    [
        [[0.2, 0.5, 0.1, 0.1, 0.1], [0.1, 0.1, 0.4, 0.1, 0.3]],
        [[0.3, 0.1, 0.3, 0.2, 0.1], [0.1, 0.2, 0.1, 0.2, 0.4]],
        [[0.1, 0.2, 0.2, 0.4, 0.1], [0.5, 0.1, 0.1, 0.1, 0.2]],
        [[0.2, 0.2, 0.2, 0.2, 0.2], [0.1, 0.3, 0.3, 0.1, 0.2]],
        [[0.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0, 1.0]],
    ]
)

# R[s, a, s']: a base reward for (s, a) plus a bonus or penalty for ending the episode;
# the terminal state pays nothing.
_BASE = np.array([[1.0, -0.5], [0.0, 2.0], [-1.0, 0.5], [0.5, 1.5], [0.0, 0.0]])
_ENDING = np.array([[-2.0, 1.0], [0.5, -1.5], [3.0, -1.0], [-0.5, 2.0], [0.0, 0.0]])
REWARDS = np.repeat(_BASE[:, :, None], NUM_STATES, axis=2)
REWARDS[:, :, TERMINAL] += _ENDING
REWARDS[TERMINAL] = 0.0

assert np.allclose(TRANSITIONS.sum(axis=-1), 1.0) and np.isclose(INITIAL.sum(), 1.0)


def expected_rewards() -> np.ndarray:
    """r̄(s, a) = Σ_s' P(s'|s, a) R(s, a, s'): all the forward recursion needs."""
    return (TRANSITIONS * REWARDS).sum(axis=-1)


def exact_objective(logits: torch.Tensor, gamma: float) -> torch.Tensor:
    """J(θ) = E[Σ_{h<H} γ^h r_h] with π(a|s) = softmax(logits[s])_a, exactly, in float64.

    Forward recursion: d_h(s) is the probability of being at s at step h; the terminal state
    absorbs its mass and pays nothing, which is exactly "the episode ended".
    """
    policy = torch.softmax(logits.to(torch.float64), dim=-1)
    transitions = torch.from_numpy(TRANSITIONS)
    mean_reward = torch.from_numpy(expected_rewards())
    state = torch.from_numpy(INITIAL)
    value = torch.zeros((), dtype=torch.float64)
    for h in range(HORIZON):
        joint = state[:, None] * policy  # P(s_h = s, a_h = a)
        value = value + gamma**h * (joint * mean_reward).sum()
        state = torch.einsum("sa,sat->t", joint, transitions)
    return value


def exact_gradient(logits: torch.Tensor, gamma: float) -> torch.Tensor:
    """∇J(θ) as a flat float64 vector in the order of ``TabularSoftmaxPolicy.parameters()``."""
    theta = logits.detach().to(torch.float64).requires_grad_(True)
    (gradient,) = torch.autograd.grad(exact_objective(theta, gamma), theta)
    return gradient.reshape(-1)


@dataclass(frozen=True, kw_only=True)
class Enumeration:
    """Every trajectory of positive probability, time-major [H, N] like a TrajectoryBatch
    (dead steps: terminal observation, action 0, reward 0, not alive)."""

    obs: np.ndarray  # [H, N] int64
    actions: np.ndarray  # [H, N] int64
    rewards: np.ndarray  # [H, N] float64
    alive: np.ndarray  # [H, N] bool
    probability: np.ndarray  # [N] float64, sums to 1


def enumerate_trajectories(logits: torch.Tensor) -> Enumeration:
    """All trajectories under π = softmax(logits), built breadth-first.

    A path that is still alive at step h branches into every (a, s') of positive probability;
    a finished one is padded with one dead step. This never uses :func:`exact_objective`, so
    the two cross-check each other.
    """
    policy = torch.softmax(logits.detach().to(torch.float64), dim=-1).numpy()
    start = np.flatnonzero(INITIAL > 0)
    obs_rows: list[np.ndarray] = []
    action_rows: list[np.ndarray] = []
    reward_rows: list[np.ndarray] = []
    alive_rows: list[np.ndarray] = []
    state = start.astype(np.int64)
    probability = INITIAL[start].copy()
    for _ in range(HORIZON):
        live = state != TERMINAL
        # Branch the live paths into every (a, s'); keep each dead path once.
        parent_live = np.flatnonzero(live)
        action, next_state = np.meshgrid(
            np.arange(NUM_ACTIONS), np.arange(NUM_STATES), indexing="ij"
        )
        action, next_state = action.ravel(), next_state.ravel()
        parents = np.repeat(parent_live, action.size)
        acts = np.tile(action, parent_live.size)
        nexts = np.tile(next_state, parent_live.size)
        branch_prob = (
            probability[parents]
            * policy[state[parents], acts]
            * TRANSITIONS[state[parents], acts, nexts]
        )
        keep = branch_prob > 0
        parents, acts, nexts, branch_prob = (
            parents[keep],
            acts[keep],
            nexts[keep],
            branch_prob[keep],
        )
        dead = np.flatnonzero(~live)
        order = np.concatenate([parents, dead])
        # Re-index the history to the new set of paths, then append this step.
        obs_rows = [row[order] for row in obs_rows]
        action_rows = [row[order] for row in action_rows]
        reward_rows = [row[order] for row in reward_rows]
        alive_rows = [row[order] for row in alive_rows]
        obs_rows.append(state[order])
        action_rows.append(np.concatenate([acts, np.zeros(dead.size, dtype=np.int64)]))
        reward_rows.append(
            np.concatenate([REWARDS[state[parents], acts, nexts], np.zeros(dead.size)])
        )
        alive_rows.append(np.concatenate([np.ones(parents.size, bool), np.zeros(dead.size, bool)]))
        state = np.concatenate([nexts, np.full(dead.size, TERMINAL)]).astype(np.int64)
        probability = np.concatenate([branch_prob, probability[dead]])
    return Enumeration(
        obs=np.stack(obs_rows),
        actions=np.stack(action_rows).astype(np.int64),
        rewards=np.stack(reward_rows),
        alive=np.stack(alive_rows),
        probability=probability,
    )


def _categorical(cdf_rows: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """One draw per row by inverting its CDF (the last column is left out so rounding can
    never give an index past the end)."""
    return (uniforms[:, None] > cdf_rows[:, :-1]).sum(axis=-1).astype(np.int64)


class TabularMDPBatchEnv:
    """The MDP above as a :class:`fedhpg.envs.base.BatchEnv` of ``num_envs`` copies.

    ## Observation / action space
    ``Discrete(5)`` states (4 is terminal), ``Discrete(2)`` actions.

    ## Episode end
    ``terminated`` on entering the terminal state; ``truncated`` after ``HORIZON`` steps.
    Finished copies stay in the (absorbing, reward-free) terminal state.
    """

    def __init__(self, num_envs: int) -> None:
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(NUM_STATES)
        self.single_action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._cdf = TRANSITIONS.cumsum(axis=-1)
        self._rng = np.random.default_rng(0)
        self._state = np.full(num_envs, TERMINAL, dtype=np.int64)
        self._steps = 0

    def reset(self, *, seed: int) -> np.ndarray:
        self._rng = np.random.default_rng(seed)
        cdf = np.broadcast_to(INITIAL.cumsum(), (self.num_envs, NUM_STATES))
        self._state = _categorical(cdf, self._rng.random(self.num_envs))
        self._steps = 0
        return self._state.copy()

    def step(self, actions: np.ndarray) -> BatchStep:
        actions = np.asarray(actions, dtype=np.int64)
        previous = self._state
        self._state = _categorical(self._cdf[previous, actions], self._rng.random(self.num_envs))
        self._steps += 1
        terminated = self._state == TERMINAL
        return BatchStep(
            obs=self._state.copy(),
            reward=REWARDS[previous, actions, self._state].astype(np.float64),
            terminated=terminated,
            truncated=np.full(self.num_envs, self._steps >= HORIZON) & ~terminated,
            success=np.zeros(self.num_envs, dtype=bool),
        )

    def close(self) -> None:
        pass


def seeded_policy(seed: int, scale: float = 1.0) -> TabularSoftmaxPolicy:
    """A policy with non-uniform logits (N(0, scale²), seeded): at θ = 0 symmetries could hide
    a wrong sign or a swapped action."""
    policy = TabularSoftmaxPolicy(num_states=NUM_STATES, num_actions=NUM_ACTIONS)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        policy.logits.copy_(scale * torch.randn(NUM_STATES, NUM_ACTIONS, generator=generator))
    return policy


def sample_batches(
    policy: TabularSoftmaxPolicy, *, batch_size: int, num_batches: int, seed: int
) -> list[TrajectoryBatch]:
    """``num_batches`` independent batches from the real sampler, each padded only to its own
    longest trajectory (as an agent would see them), from one seeded generator."""
    rng = np.random.default_rng(seed)
    env = TabularMDPBatchEnv(batch_size)
    return [sample_trajectories(env, policy, rng, horizon=HORIZON) for _ in range(num_batches)]


CoefficientFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(rewards [T, B], alive [T, B]) -> coefficients [T, B], hyper-parameters already bound."""
