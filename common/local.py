"""Pieces every local-update rule shares: batch gradients, ascent steps, bookkeeping."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from fedhpg.common.config import AlgoConfig
from fedhpg.common.estimators import estimate_gradient, estimator_coefficients
from fedhpg.common.policies import Policy
from fedhpg.common.rollout import TrajectoryBatch

TrajectorySource = Callable[[int], TrajectoryBatch]
"""n -> n fresh trajectories sampled with the policy's current θ."""

IterationHook = Callable[[int, float, int], None]
"""(iteration, compute seconds (thread CPU time), env steps) -> None; after every iteration."""


def batch_tensors(batch: TrajectoryBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations and actions as tensors, without copying the numpy buffers."""
    return torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)


def batch_gradient(
    policy: Policy,
    batch: TrajectoryBatch,
    *,
    algo: AlgoConfig,
    gamma: float,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """(1/B) Σ_b g(τ_b | θ) with the configured estimator and baseline."""
    coefficients = estimator_coefficients(
        algo.estimator,  # type: ignore[arg-type]
        torch.from_numpy(batch.rewards),
        torch.from_numpy(batch.alive),
        gamma=gamma,
        baseline=algo.baseline,  # type: ignore[arg-type]
        weights=weights,
    )
    obs, actions = batch_tensors(batch)
    return estimate_gradient(policy, obs, actions, coefficients)


class PlainAscent:
    """θ ← θ + η g: the paper's update (Algorithm 1 line 8, Algorithm 2 line 10)."""

    def __init__(self, step_size: float) -> None:
        self.step_size = step_size

    def direction(self, gradient: torch.Tensor) -> torch.Tensor:
        return self.step_size * gradient


class AdamAscent:
    """Adam on the flat parameter vector (ascent), state reset every round.

    Written out rather than taken from ``torch.optim``: the first ``torch.optim`` step imports
    torch's compiler stack (~1 s per process), and this keeps every operation explicit.
    """

    def __init__(
        self, step_size: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ) -> None:
        self.step_size, self.betas, self.eps = step_size, betas, eps
        self.steps = 0
        self.first: torch.Tensor | None = None
        self.second: torch.Tensor | None = None

    def direction(self, gradient: torch.Tensor) -> torch.Tensor:
        beta1, beta2 = self.betas
        if self.first is None or self.second is None:
            self.first, self.second = torch.zeros_like(gradient), torch.zeros_like(gradient)
        self.steps += 1
        self.first = beta1 * self.first + (1 - beta1) * gradient
        self.second = beta2 * self.second + (1 - beta2) * gradient * gradient
        first_hat = self.first / (1 - beta1**self.steps)
        second_hat = self.second / (1 - beta2**self.steps)
        return self.step_size * first_hat / (second_hat.sqrt() + self.eps)

    def state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """(scalars, arrays) that :meth:`restore` takes back: a checkpoint's share."""
        if self.first is None or self.second is None:
            return {"steps": self.steps}, {}
        # Views, not copies: direction() replaces the moment tensors, never writes into them.
        return {"steps": self.steps}, {"first": self.first.numpy(), "second": self.second.numpy()}

    def restore(self, scalars: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.steps = int(scalars["steps"])
        if self.steps:
            self.first = torch.from_numpy(np.array(arrays["first"]))
            self.second = torch.from_numpy(np.array(arrays["second"]))


Optimizer = PlainAscent | AdamAscent


def make_optimizer(algo: AlgoConfig) -> Optimizer:
    """Gradient *ascent*: plain steps θ += η g (the paper) or Adam, fresh every round."""
    if algo.optimizer == "sgd":
        return PlainAscent(algo.step_size)
    if algo.optimizer == "adam":
        return AdamAscent(algo.step_size)
    raise ValueError(f"algo.optimizer must be 'sgd' or 'adam', got {algo.optimizer!r}")


def apply_ascent(policy: Policy, optimizer: Optimizer, gradient: torch.Tensor) -> None:
    """One ascent step on the policy's flat parameter vector."""
    theta = torch.nn.utils.parameters_to_vector(policy.parameters()).detach()
    with torch.no_grad():
        torch.nn.utils.vector_to_parameters(
            theta + optimizer.direction(gradient), policy.parameters()
        )


@dataclass(frozen=True, kw_only=True)
class LocalResult:
    """What a local update returns to the server."""

    theta: torch.Tensor
    trajectories: int
    env_steps: int
    train_return: float
    """Mean undiscounted return of the trajectories sampled this round."""
    compute_s: float
    """CPU time of the local update on this thread (sampling + estimation + steps): the
    agent's own work, unaffected by other processes competing for the machine."""
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class LocalTally:
    """Running totals over a round's local iterations."""

    trajectories: int = 0
    env_steps: int = 0
    return_sum: float = 0.0
    compute_s: float = 0.0
    clipped: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def add(self, batch: TrajectoryBatch, *, compute_s: float, clipped: bool = False) -> None:
        self.trajectories += batch.num_trajectories
        self.env_steps += batch.num_steps
        self.return_sum += float(np.sum(batch.returns()))
        self.compute_s += compute_s
        self.clipped += int(clipped)

    def result(self, theta: torch.Tensor) -> LocalResult:
        return LocalResult(
            theta=theta,
            trajectories=self.trajectories,
            env_steps=self.env_steps,
            train_return=self.return_sum / max(self.trajectories, 1),
            compute_s=self.compute_s,
            extra={"grad_clipped": self.clipped, **self.extra},
        )
