"""A tiny finite-horizon tabular MDP whose objective J(θ) is computed exactly.

Three live states, one absorbing terminal state, two actions, stochastic transitions and a
horizon of 4: small enough for exact dynamic programming in float64 torch (so ∇J comes from
autograd), rich enough that trajectories end early, which exercises the alive masks.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from oracle import TrajectoryBatch, sample_trajectories

from fedhpg.common.learning.estimators import per_trajectory_gradients
from fedhpg.common.learning.policies import TabularSoftmaxPolicy
from fedhpg.envs.base import BatchStep

BATCH = 8
GROUPS = 4000
Z_LIMIT = 4.0  # standard errors: ~1e-3 false-alarm chance over 16 coordinates
NUM_STATES = 4  # 0, 1, 2 live; 3 terminal
NUM_ACTIONS = 2
TERMINAL = 3
HORIZON = 4
INITIAL = np.array([0.5, 0.3, 0.2, 0.0])
# P[s, a, s'] for live s; each row sums to 1.
TRANSITIONS = np.array(
    [
        [[0.1, 0.6, 0.2, 0.1], [0.5, 0.1, 0.3, 0.1]],
        [[0.3, 0.2, 0.4, 0.1], [0.1, 0.1, 0.2, 0.6]],
        [[0.6, 0.2, 0.1, 0.1], [0.2, 0.5, 0.1, 0.2]],
        [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]],
    ]
)
# r(s, a): reward for taking a in s; the terminal state pays nothing.
REWARDS = np.array([[1.0, -0.5], [0.0, 2.0], [-1.0, 0.5], [0.0, 0.0]])


def exact_objective(logits: torch.Tensor, gamma: float) -> torch.Tensor:
    """J(θ) = E[Σ_{h<H} γ^h r(s_h, a_h)] by forward recursion over state distributions."""
    policy = torch.softmax(logits.double(), dim=-1)
    transitions = torch.from_numpy(TRANSITIONS)
    rewards = torch.from_numpy(REWARDS)
    state = torch.from_numpy(INITIAL)
    value = torch.zeros((), dtype=torch.float64)
    for h in range(HORIZON):
        joint = state[:, None] * policy  # P(s_h = s, a_h = a), terminal mass carries no reward
        value = value + gamma**h * (joint * rewards).sum()
        state = torch.einsum("sa,sat->t", joint, transitions)
    return value


def exact_gradient(logits: torch.Tensor, gamma: float) -> torch.Tensor:
    theta = logits.detach().double().requires_grad_(True)
    (grad,) = torch.autograd.grad(exact_objective(theta, gamma), theta)
    return grad.reshape(-1)


def trajectory_log_probability(
    logits: torch.Tensor, obs: np.ndarray, actions: np.ndarray, alive: np.ndarray
) -> np.ndarray:
    """log p(τ|θ) including the initial distribution and the dynamics, per trajectory [B]."""
    log_pi = torch.log_softmax(logits.detach().double(), dim=-1).numpy()
    total = np.log(INITIAL[obs[0]])
    for t in range(obs.shape[0]):
        live = alive[t]
        total = total + np.where(live, log_pi[obs[t], actions[t]], 0.0)
        if t + 1 < obs.shape[0]:
            step = TRANSITIONS[obs[t], actions[t], obs[t + 1]]
            with np.errstate(divide="ignore"):  # log 0 of padding steps, masked away
                total = total + np.where(alive[t + 1], np.log(step), 0.0)
    return total


class ExactMDPBatchEnv:
    """The MDP above as a BatchEnv for the real sampler."""

    def __init__(self, num_envs: int) -> None:
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(NUM_STATES)
        self.single_action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._cumulative = TRANSITIONS.cumsum(axis=-1)
        self._state = np.zeros(num_envs, dtype=np.int64)
        self._steps = 0
        self._rng = np.random.default_rng(0)

    def reset(self, *, seed: int) -> np.ndarray:
        self._rng = np.random.default_rng(seed)
        self._state = np.minimum(
            (self._rng.random(self.num_envs)[:, None] > INITIAL.cumsum()).sum(axis=1), 2
        ).astype(np.int64)
        self._steps = 0
        return self._state.copy()

    def step(self, actions: np.ndarray) -> BatchStep:
        reward = REWARDS[self._state, actions]
        cumulative = self._cumulative[self._state, actions]
        uniforms = self._rng.random(self.num_envs)
        self._state = np.minimum((uniforms[:, None] > cumulative).sum(axis=1), NUM_STATES - 1)
        self._steps += 1
        terminated = self._state == TERMINAL
        return BatchStep(
            obs=self._state.copy(),
            reward=reward,
            terminated=terminated,
            truncated=np.full(self.num_envs, self._steps >= HORIZON) & ~terminated,
            success=np.zeros(self.num_envs, dtype=bool),
        )

    def close(self) -> None:
        pass


Coefficients = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def make_policy(seed: int = 0) -> TabularSoftmaxPolicy:
    policy = TabularSoftmaxPolicy(num_states=NUM_STATES, num_actions=NUM_ACTIONS)
    with torch.no_grad():
        policy.logits.copy_(
            torch.randn(NUM_STATES, NUM_ACTIONS, generator=torch.Generator().manual_seed(seed))
        )
    return policy


def sample(policy: TabularSoftmaxPolicy, count: int, seed: int) -> TrajectoryBatch:
    return sample_trajectories(
        ExactMDPBatchEnv(count), policy, np.random.default_rng(seed), horizon=HORIZON
    )


def batch_estimates(
    policy: TabularSoftmaxPolicy,
    trajectories: TrajectoryBatch,
    coefficients: Coefficients,
    *,
    actions: np.ndarray | None = None,
    batch: int = BATCH,
) -> torch.Tensor:
    """[G, d]: the estimate of each group of ``batch`` consecutive trajectories, with the
    coefficients (and so any baseline) computed within the group."""
    rewards = torch.from_numpy(trajectories.rewards)
    alive = torch.from_numpy(trajectories.alive)
    coef = torch.cat(
        [
            coefficients(rewards[:, i : i + batch], alive[:, i : i + batch])
            for i in range(0, rewards.shape[1], batch)
        ],
        dim=1,
    )
    obs = torch.from_numpy(trajectories.obs)
    acts = torch.from_numpy(trajectories.actions if actions is None else actions)
    per_trajectory = per_trajectory_gradients(policy, obs, acts, coef).double()
    return per_trajectory.reshape(-1, batch, per_trajectory.shape[1]).mean(dim=1)


def max_standard_errors(estimates: torch.Tensor, exact: torch.Tensor) -> float:
    """Largest |mean − exact| / standard error over the coordinates (exactly-zero coordinates,
    such as the never-visited terminal state's logits, must be exactly zero)."""
    mean = estimates.mean(dim=0)
    stderr = estimates.std(dim=0) / estimates.shape[0] ** 0.5
    degenerate = stderr == 0
    assert torch.all(mean[degenerate] == exact[degenerate]), "zero-variance coordinate is off"
    z = (mean - exact).abs()[~degenerate] / stderr[~degenerate]
    return float(z.max())
