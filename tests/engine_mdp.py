"""Any test environment as agents' variants on the real engine (its gymnasium path).

:func:`mdp_engine` gives an :class:`~fedhpg.common.learning.engine.engine.Engine` of ``rows`` agents
that all step copies of one :class:`~fedhpg.envs.base.BatchEnv` (a tabular MDP with an exact
gradient, say), so a test samples thousands of independent batches in one call and checks
what the algorithms are built of against exact answers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym

from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.base import BatchEnv, EnvVariant


@dataclass(frozen=True, kw_only=True)
class BatchEnvVariant(EnvVariant):
    """A variant whose copies come from ``factory(num_envs)``, episodes of ``horizon``."""

    factory: Callable[[int], BatchEnv]
    horizon: int

    def make_batch_env(self, num_envs: int) -> BatchEnv:
        return self.factory(num_envs)

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        batch = self.factory(1)
        env = gym.Env()
        env.observation_space = batch.single_observation_space
        env.action_space = batch.single_action_space
        return env

    @property
    def max_episode_steps(self) -> int:
        return self.horizon


def mdp_engine(
    factory: Callable[[int], BatchEnv],
    horizon: int,
    rows: int,
    *,
    gamma: float,
    estimator: str = "gpomdp",
    baseline: str = "none",
    overrides: tuple[str, ...] = (),
) -> Engine:
    """An engine of ``rows`` agents 0 … rows−1 on copies from ``factory``, discount ``gamma``."""
    run = compose(
        [
            f"algo.estimator={estimator}", f"algo.baseline={baseline}", f"env.gamma={gamma}",
            f"agents.num_agents={rows}", "agents.budget.batch_size=[8]",
            "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
            *overrides,
        ]
    )  # fmt: skip
    variant = BatchEnvVariant(family="mdp", index=0, gamma=gamma, factory=factory, horizon=horizon)
    return Engine(run, dict.fromkeys(range(rows), variant))
