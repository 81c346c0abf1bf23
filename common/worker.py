"""One agent's learning side: its environment variant, policy, random streams and updates.

The agent process wraps a :class:`LocalWorker` with sockets and device emulation; the
in-process pool drives K of them directly. Both therefore compute exactly the same numbers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
import torch

from fedhpg.common.algorithms import LocalContext
from fedhpg.common.attacks import (
    UPDATE_ATTACKS,
    attack_of,
    corrupt_batch,
    corrupt_update,
    random_action_sampler,
)
from fedhpg.common.components import AgentProfile, resolve_algorithm
from fedhpg.common.config import RunConfig
from fedhpg.common.local import TrajectorySource, counting_gradients
from fedhpg.common.policies import Policy, get_flat_params, make_policy, set_flat_params
from fedhpg.common.rollout import TrajectoryBatch, sample_trajectories
from fedhpg.common.types import EvaluationStats, LocalResult
from fedhpg.common.variants import discount, training_horizon
from fedhpg.envs.base import BatchEnv, EnvVariant


class Stream(IntEnum):
    """Purposes of the per-(seed, agent, round) random streams."""

    TRAIN = 0
    EVALUATE = 1
    ATTACK = 2


def random_stream(
    seed: int, agent_index: int, round_index: int, purpose: Stream
) -> np.random.Generator:
    """A stream that depends only on (seed, agent, round, purpose).

    A restarted agent, or the same agent in another process, redoes exactly the same work.
    """
    return np.random.default_rng([seed, agent_index, round_index, int(purpose)])


def build_policy(variant: EnvVariant, run: RunConfig) -> Policy:
    """The run's policy for the variant's spaces, initialised from the run seed alone."""
    env = variant.make_env()
    # Only the CPU generator, saved and restored by hand: torch.random.fork_rng() and
    # torch.manual_seed() also reach for every CUDA device, which initialises CUDA where torch
    # has it, and CUDA then refuses every process forked afterwards (fedhpg-run calls this
    # before it forks the server and the agents, and each of them calls it again).
    state = torch.default_generator.get_state()
    try:
        torch.default_generator.manual_seed(run.seed)
        return make_policy(env.observation_space, env.action_space, run.policy)
    finally:
        torch.default_generator.set_state(state)
        env.close()


def initial_theta(variant: EnvVariant, run: RunConfig) -> torch.Tensor:
    """θ̃_0, the server's starting point: deterministic in the run seed."""
    return get_flat_params(build_policy(variant, run))


@dataclass(frozen=True)
class IterationWork:
    """The work of one local iteration, as the device emulation prices it."""

    iteration: int
    compute_s: float
    """Thread CPU time the iteration took here (what the measured clock stretches)."""
    env_steps: int
    grad_steps: int
    """Trajectory steps differentiated (a VR step differentiates its mini-batch twice)."""


WorkHook = Callable[[IterationWork], None]


class LocalWorker:
    """Agent ``index`` of a run: samples, estimates and steps in its own environment."""

    def __init__(
        self, *, index: int, variant: EnvVariant, run: RunConfig, profile: AgentProfile
    ) -> None:
        self.index = index
        self.variant = variant
        self.run = run
        self.profile = profile
        self.algorithm, self.params = resolve_algorithm(run)
        self.attack = attack_of(run.attack, index)
        self.policy = build_policy(variant, run)
        self.horizon = training_horizon(run, variant)
        self.gamma = discount(run, variant)
        self._batch_envs: dict[int, BatchEnv] = {}

    @property
    def num_params(self) -> int:
        return self.policy.num_params

    def _batch_env(self, num_envs: int) -> BatchEnv:
        if num_envs not in self._batch_envs:
            self._batch_envs[num_envs] = self.variant.make_batch_env(num_envs)
        return self._batch_envs[num_envs]

    def _sampler(self, rng: np.random.Generator) -> TrajectorySource:
        def sample(num_trajectories: int) -> TrajectoryBatch:
            env = self._batch_env(num_trajectories)
            actions = None
            if self.attack == "random_action":
                actions = random_action_sampler(env.single_action_space, self.policy.sampler())
            batch = sample_trajectories(
                env, self.policy, rng, horizon=self.horizon, sampler=actions
            )
            return corrupt_batch(self.attack, batch)

        return sample

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        *,
        on_iteration: WorkHook | None = None,
        budget: Any = None,
    ) -> LocalResult:
        """One round's local update from the server's θ̃ (the run's algorithm); ``budget``:
        the round's planned budget instead of the configured one."""
        rng = random_stream(self.run.seed, self.index, round_index, Stream.TRAIN)
        with counting_gradients() as gradients:

            def hook(iteration: int, compute_s: float, env_steps: int) -> None:
                if on_iteration is not None:
                    work = IterationWork(iteration, compute_s, env_steps, gradients.take())
                    on_iteration(work)

            context = LocalContext(
                policy=self.policy,
                sample=self._sampler(rng),
                settings=self.run.algo,
                gamma=self.gamma,
                on_iteration=hook,
                seed=self.run.seed,
                round_index=round_index,
            )
            budget = self.profile.budget if budget is None else budget
            result = self.algorithm.local_update(theta, context, self.params, budget)
        if self.attack in UPDATE_ATTACKS:
            attack_rng = random_stream(self.run.seed, self.index, round_index, Stream.ATTACK)
            sent = corrupt_update(self.attack, theta, result.theta, self.run.attack, attack_rng)
            result = dataclasses.replace(result, theta=sent)
        return result

    def evaluate(self, round_index: int, theta: torch.Tensor, episodes: int) -> EvaluationStats:
        """Return and success rate of the unified policy over ``episodes`` episodes here."""
        set_flat_params(self.policy, theta)
        rng = random_stream(self.run.seed, self.index, round_index, Stream.EVALUATE)
        batch = sample_trajectories(
            self._batch_env(episodes),
            self.policy,
            rng,
            horizon=self.run.eval.horizon or self.horizon,
            greedy=self.run.eval.greedy,
        )
        returns = batch.returns()
        return EvaluationStats(
            return_mean=float(returns.mean()),
            return_std=float(returns.std()),
            discounted_return_mean=float(batch.returns(self.gamma).mean()),
            success_rate=float(batch.success.mean()),
            length_mean=float(batch.lengths.mean()),
            episodes=int(batch.num_trajectories),
        )

    def close(self) -> None:
        for env in self._batch_envs.values():
            env.close()
        self._batch_envs.clear()
