"""The engine's primitives against exact answers, and its rows against placement.

- Unbiased: on tabular MDPs with an exact ∇J (with a terminal state, and without one), the
  engine's batch estimates (sampling, the shared coefficients, the rows' autograd gradients:
  every algorithm's building block) average to ∇J within 4 standard errors, for both
  estimators, with and without the baseline, over thousands of rows sampled at once.
- Faithful: on identical trajectories, each row's estimate equals the per-agent autograd
  oracle (``estimate_gradient`` on that agent's columns alone) to float32 rounding.
- Draws: the engine's actions follow the policy's probabilities (a chi-square test).
- Placement: an agent's θ_k is bit for bit the same alone, beside others with other budgets,
  or in any order, for every algorithm, on a gymnasium family and a torch family.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch
from engine_mdp import mdp_engine
from tabular_mdp import HORIZON as TABULAR_HORIZON
from tabular_mdp import TabularMDPBatchEnv, exact_gradient, seeded_policy

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.estimators import estimate_gradient, estimator_coefficients
from fedhpg.common.learning.group import TIMING_STATS, EngineGroup
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.base import BatchStep

ROWS = 3000
BATCH = 8
Z_LIMIT = 4.0
STDERR_FLOOR = 1e-9


class _NoTerminal:
    """A 3-state MDP that never ends before its horizon of 4 (rewards r(s, a))."""

    STATES, ACTIONS, HORIZON = 3, 2, 4
    INITIAL = np.array([0.5, 0.3, 0.2])
    TRANSITIONS = np.array(
        [
            [[0.2, 0.7, 0.1], [0.5, 0.2, 0.3]],
            [[0.3, 0.3, 0.4], [0.1, 0.1, 0.8]],
            [[0.6, 0.3, 0.1], [0.2, 0.5, 0.3]],
        ]
    )
    REWARDS = np.array([[1.0, -0.5], [0.0, 2.0], [-1.0, 0.5]])

    @classmethod
    def exact_gradient(cls, logits: torch.Tensor, gamma: float) -> torch.Tensor:
        theta = logits.detach().double().requires_grad_(True)
        policy = torch.softmax(theta, dim=-1)
        state = torch.from_numpy(cls.INITIAL)
        value = torch.zeros((), dtype=torch.float64)
        for h in range(cls.HORIZON):
            joint = state[:, None] * policy
            value = value + gamma**h * (joint * torch.from_numpy(cls.REWARDS)).sum()
            state = torch.einsum("sa,sat->t", joint, torch.from_numpy(cls.TRANSITIONS))
        (gradient,) = torch.autograd.grad(value, theta)
        return gradient.reshape(-1)


class _NoTerminalBatchEnv:
    def __init__(self, num_envs: int) -> None:
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(_NoTerminal.STATES)
        self.single_action_space = gym.spaces.Discrete(_NoTerminal.ACTIONS)
        self._rng = np.random.default_rng(0)
        self._state = np.zeros(num_envs, dtype=np.int64)

    def reset(self, *, seed: int) -> np.ndarray:
        self._rng = np.random.default_rng(seed)
        u = self._rng.random(self.num_envs)
        self._state = (u[:, None] > _NoTerminal.INITIAL.cumsum()[:-1]).sum(axis=1)
        return self._state.copy()

    def step(self, actions: np.ndarray) -> BatchStep:
        reward = _NoTerminal.REWARDS[self._state, actions]
        cdf = _NoTerminal.TRANSITIONS[self._state, actions].cumsum(axis=1)
        u = self._rng.random(self.num_envs)
        self._state = (u[:, None] > cdf[:, :-1]).sum(axis=1)
        none = np.zeros(self.num_envs, dtype=bool)
        return BatchStep(self._state.copy(), reward.astype(np.float64), none, none, none)

    def close(self) -> None:
        pass


def _engine(
    estimator: str, baseline: str, gamma: float, rows: int, terminal: bool = True
) -> Engine:
    if terminal:
        return mdp_engine(TabularMDPBatchEnv, TABULAR_HORIZON, rows, gamma=gamma,
                          estimator=estimator, baseline=baseline)  # fmt: skip
    return mdp_engine(_NoTerminalBatchEnv, _NoTerminal.HORIZON, rows, gamma=gamma,
                      estimator=estimator, baseline=baseline)  # fmt: skip


@pytest.mark.parametrize("terminal", [True, False], ids=["terminal", "no-terminal"])
@pytest.mark.parametrize("estimator", ["reinforce", "gpomdp"])
@pytest.mark.parametrize("baseline", ["none", "mean"])
def test_engine_estimates_are_unbiased(estimator: str, baseline: str, terminal: bool) -> None:
    gamma = 0.9
    states = 5 if terminal else _NoTerminal.STATES
    policy = seeded_policy(3) if terminal else None
    logits = (
        policy.logits.detach()
        if policy is not None
        else torch.randn(states, 2, generator=torch.Generator().manual_seed(3))
    )
    exact = exact_gradient(logits, gamma) if terminal else _NoTerminal.exact_gradient(logits, gamma)
    engine = _engine(estimator, baseline, gamma, ROWS, terminal)
    rows = engine.begin(1, logits.reshape(-1), list(range(ROWS)))
    batch = rows.sample(rows.theta, torch.full((ROWS,), BATCH), iteration=0)
    estimates = rows.mean_gradients(rows.theta, batch).double()
    error = (estimates.mean(dim=0) - exact).abs()
    stderr = (estimates.std(dim=0) / ROWS**0.5).clamp_min(STDERR_FLOOR)
    assert float((error / stderr).max()) < Z_LIMIT, (error / stderr).tolist()
    # power: the same check catches a wrong sign on the baseline-free coefficients
    wrong = rows.gradients(rows.theta, batch, -rows.coefficients(batch)) / BATCH
    assert float(((wrong.double().mean(0) - exact).abs() / stderr).max()) > 6.0


@pytest.mark.parametrize("estimator", ["reinforce", "gpomdp"])
@pytest.mark.parametrize("baseline", ["none", "mean"])
def test_each_row_equals_the_per_agent_autograd_oracle(estimator: str, baseline: str) -> None:
    """Rows with different batch sizes side by side: each row's estimate is what the
    single-agent autograd path computes from that row's trajectories alone."""
    engine = _engine(estimator, baseline, 0.95, 5)
    logits = seeded_policy(7).logits.detach()
    rows = engine.begin(2, logits.reshape(-1), list(range(5)))
    theta = rows.theta + 0.1 * torch.randn(
        rows.theta.shape, generator=torch.Generator().manual_seed(1)
    )
    counts = torch.tensor([3, 1, 6, 2, 4])
    batch = rows.sample(theta, counts, iteration=0)
    gradients = rows.mean_gradients(theta, batch)
    for row in range(5):
        mine = batch.owner == row
        policy = seeded_policy(0)
        with torch.no_grad():
            policy.logits.copy_(theta[row].reshape(policy.logits.shape))
        coef = estimator_coefficients(
            estimator, batch.rewards[:, mine], batch.alive[:, mine], gamma=0.95,
            baseline=baseline,
        )  # fmt: skip
        oracle = estimate_gradient(policy, batch.obs[:, mine], batch.actions[:, mine], coef)
        torch.testing.assert_close(gradients[row], oracle, rtol=1e-5, atol=1e-6)


def test_action_draws_follow_the_policy() -> None:
    """Categorical draws of the engine's sampler, counted per state over 20,000 decisions,
    match softmax(θ[s]) by a chi-square test."""
    engine = _engine("gpomdp", "none", 1.0, 2500)
    logits = seeded_policy(11, scale=1.5).logits.detach()
    rows = engine.begin(3, logits.reshape(-1), list(range(2500)))
    batch = rows.sample(rows.theta, torch.full((2500,), 4), iteration=0)
    probabilities = torch.softmax(logits.double(), dim=-1)
    obs, actions = batch.obs[batch.alive], batch.actions[batch.alive]
    for state in range(4):
        taken = actions[obs == state]
        observed = torch.bincount(taken, minlength=2).double()
        expected = probabilities[state] * observed.sum()
        statistic = float(((observed - expected) ** 2 / expected).sum())
        p_value = float(torch.special.gammaincc(torch.tensor(0.5), torch.tensor(statistic / 2)))
        assert p_value > 1e-4, (state, observed.tolist(), expected.tolist())
        assert observed.sum() > 1000, "too few decisions in this state for the test's power"


FEDHPG_BUDGETS = ["agents.budget.batch_size=[3,5,4,2,6]", "agents.budget.local_iters=[1,2,3,1,2]"]
VR_BUDGETS = [
    "agents.budget.batch_size=[3,5,4,2,6]", "agents.budget.inner_steps=[1,2,2,1,3]",
    "agents.budget.mini_batch_size=[2,3,2,4,2]", "agents.budget.local_iters=[1]",
]  # fmt: skip
PLACEMENT_RUNS = {
    "fedhpg-gridworld": ["algo=fedhpg", *FEDHPG_BUDGETS],
    "fedhpgvr-gridworld": ["algo=fedhpgvr", *VR_BUDGETS],
    "fedpgbr-cartpole": [
        "env=cartpole", "algo=fedpgbr", "strategy=fedpgbr", "algo.engine=torch", *FEDHPG_BUDGETS,
    ],
    "fedhpg-cartpole-torch": [
        "env=cartpole", "algo.engine=torch", "policy.hidden=[8]", *FEDHPG_BUDGETS,
    ],
    "fedhpgvr-pendulum": ["env=pendulum", "algo=fedhpgvr", "policy.hidden=[8]", *VR_BUDGETS],
    "attacks-gridworld": ["attack=random_action", "attack.agents=[1,2]", *FEDHPG_BUDGETS],
}  # fmt: skip


@pytest.mark.parametrize("overrides", list(PLACEMENT_RUNS.values()), ids=list(PLACEMENT_RUNS))
def test_an_agents_theta_does_not_depend_on_its_company(overrides: list[str]) -> None:
    """Agent 2 trained alone, beside agents 0..4 (other budgets), and beside 1 and 3 only:
    its θ_2 and statistics are the same, bit for bit."""
    run = compose([
        *overrides, "agents.num_agents=5", "agents.speeds=[1]", "agents.step_delays_s=[0]",
        "env.horizon=60",
    ])  # fmt: skip
    theta = initial_theta(variants_of(run, [0])[0], run)
    trained = {}
    for company in ([2], [0, 1, 2, 3, 4], [3, 2, 1]):
        group = EngineGroup(run, variants_of(run, company))
        trained[tuple(company)] = group.train(4, theta, company).result
        group.close()
    first, *others = (
        (torch.from_numpy(result.theta_of(2)), dataclasses.replace(
            result.stats_of(2), compute_s=0.0, algorithm={
                name: value for name, value in result.stats_of(2).algorithm.items()
                if name not in TIMING_STATS
            },
        ))  # CPU times vary between any two runs
        for result in trained.values()
    )  # fmt: skip
    for other in others:
        assert torch.equal(first[0], other[0])
        assert other[1] == first[1]


@pytest.mark.parametrize("agents", [1, 3, 8, 9, 40])
def test_trajectory_keys_are_the_same_hashed_per_agent_or_per_trajectory(agents: int) -> None:
    """The keys of an agent's trajectories, its part hashed once per agent or with every
    trajectory: the same words."""
    from fedhpg.common.learning.randomness import Purpose, trajectory_keys

    ids = torch.arange(agents) * 37 + 5
    owner = torch.repeat_interleave(torch.arange(agents), 3)
    index = torch.arange(3 * agents) % 3
    for round_index, iteration, purpose in ((0, 0, Purpose.TRAIN), (2**40, 7, Purpose.EVALUATE)):
        spread = trajectory_keys(11, ids, round_index, purpose, iteration, index, owner)
        each = trajectory_keys(11, ids[owner], round_index, purpose, iteration, index)
        assert torch.equal(spread, each)
        assert len(set(each.tolist())) == len(each)  # distinct keys: the check can tell
