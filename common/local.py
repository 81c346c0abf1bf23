"""Pieces every local-update rule shares: batch gradients, ascent steps, bookkeeping."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from fedhpg.common.bounds import GradientMoments, gradient_moments, secant_smoothness
from fedhpg.common.config import AlgoConfig
from fedhpg.common.estimators import (
    estimate_gradient,
    estimator_coefficients,
    per_trajectory_gradients,
)
from fedhpg.common.optim import Optimizer
from fedhpg.common.policies import Policy
from fedhpg.common.rollout import TrajectoryBatch
from fedhpg.common.types import LocalResult, UpdateStats

TrajectorySource = Callable[[int], TrajectoryBatch]
"""n -> n fresh trajectories sampled with the policy's current θ."""

IterationHook = Callable[[int, float, int], None]
"""(iteration, compute seconds (thread CPU time), env steps) -> None; after every iteration."""


class GradientCount:
    """Trajectory steps differentiated so far: what the counted clock prices as gradient work.

    Counted inside :func:`batch_gradient`, which every local-update rule calls, so no rule has
    to report it; :meth:`take` gives the steps since the last call (one iteration's).
    """

    def __init__(self) -> None:
        self.steps = 0

    def take(self) -> int:
        steps, self.steps = self.steps, 0
        return steps


# Per thread: the in-process pool trains on the main thread, the agent process on its job
# thread, and each counts only the gradients its own thread computes.
_active = threading.local()


@contextmanager
def counting_gradients() -> Iterator[GradientCount]:
    """Count the trajectory steps :func:`batch_gradient` differentiates on this thread."""
    outer = getattr(_active, "count", None)
    count = _active.count = GradientCount()
    try:
        yield count
    finally:
        _active.count = outer


def batch_tensors(batch: TrajectoryBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations and actions as tensors, without copying the numpy buffers."""
    return torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)


def _coefficients(
    batch: TrajectoryBatch,
    *,
    algo: AlgoConfig,
    gamma: float,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """The configured estimator's per-step coefficients of a batch, [T, B]."""
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


def batch_gradient(
    policy: Policy,
    batch: TrajectoryBatch,
    *,
    algo: AlgoConfig,
    gamma: float,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """(1/B) Σ_b g(τ_b | θ) with the configured estimator and baseline."""
    coefficients = _coefficients(batch, algo=algo, gamma=gamma, weights=weights)
    obs, actions = batch_tensors(batch)
    count: GradientCount | None = getattr(_active, "count", None)
    if count is not None:
        count.steps += batch.num_steps
    return estimate_gradient(policy, obs, actions, coefficients)


def bound_statistics(
    policy: Policy, batch: TrajectoryBatch, *, algo: AlgoConfig, gamma: float
) -> dict[str, float]:
    """Theorem 1's constants from one batch's per-trajectory gradients at the policy's θ
    (``algo.bound_estimates``; :mod:`fedhpg.common.bounds`). Empty for a batch of one."""
    if batch.num_trajectories < 2:
        return {}
    coefficients = _coefficients(batch, algo=algo, gamma=gamma)
    obs, actions = batch_tensors(batch)
    moments = gradient_moments(per_trajectory_gradients(policy, obs, actions, coefficients))
    return bound_stats(moments)


def bound_stats(moments: GradientMoments) -> dict[str, float]:
    """The names under which an agent reports :class:`GradientMoments` (``algorithm`` stats)."""
    return {
        "bound_variance": moments.variance,
        "bound_second_moment": moments.second_moment,
        "bound_grad_norm_sq": moments.grad_norm_sq,
    }


class SmoothnessProbe:
    """``bound_smoothness``: L̂ from an agent's first two local iterations, the noise-corrected
    secant between its (unclipped) batch gradients at θ̃ and one step on
    (:func:`fedhpg.common.bounds.secant_smoothness`); nothing with one local iteration."""

    def __init__(self) -> None:
        self.points: list[tuple[torch.Tensor, torch.Tensor, float]] = []

    def add(self, theta: torch.Tensor, gradient: torch.Tensor, noise: float) -> None:
        self.points.append((theta.detach().clone(), gradient.detach().clone(), noise))

    def stats(self) -> dict[str, float]:
        if len(self.points) < 2:
            return {}
        (theta0, g0, n0), (theta1, g1, n1) = self.points[:2]
        smoothness = secant_smoothness(theta0, theta1, g0, g1, n0, n1)
        return {} if smoothness is None else {"bound_smoothness": smoothness}


def apply_ascent(policy: Policy, optimizer: Optimizer, gradient: torch.Tensor) -> None:
    """One ascent step on the policy's flat parameter vector."""
    theta = torch.nn.utils.parameters_to_vector(policy.parameters()).detach()
    with torch.no_grad():
        torch.nn.utils.vector_to_parameters(
            theta + optimizer.direction(gradient), policy.parameters()
        )


@dataclass
class LocalTally:
    """Running totals over a round's local iterations."""

    trajectories: int = 0
    env_steps: int = 0
    return_sum: float = 0.0
    compute_s: float = 0.0
    clipped: int = 0
    algorithm: dict[str, float] = field(default_factory=dict)
    """The algorithm's own statistics of the round (:attr:`UpdateStats.algorithm`)."""

    def add(self, batch: TrajectoryBatch, *, compute_s: float, clipped: bool = False) -> None:
        self.add_counts(
            batch.num_trajectories,
            batch.num_steps,
            float(np.sum(batch.returns())),
            compute_s=compute_s,
            clipped=clipped,
        )

    def add_counts(
        self,
        trajectories: int,
        env_steps: int,
        return_sum: float,
        *,
        compute_s: float,
        clipped: bool = False,
    ) -> None:
        """One iteration's totals, where no TrajectoryBatch exists (the batched engine)."""
        self.trajectories += trajectories
        self.env_steps += env_steps
        self.return_sum += return_sum
        self.compute_s += compute_s
        self.clipped += int(clipped)

    def result(self, theta: torch.Tensor) -> LocalResult:
        return LocalResult(
            theta=theta,
            stats=UpdateStats(
                trajectories=self.trajectories,
                env_steps=self.env_steps,
                train_return=self.return_sum / max(self.trajectories, 1),
                compute_s=self.compute_s,
                grad_clipped=self.clipped,
                algorithm=dict(self.algorithm),
            ),
        )
