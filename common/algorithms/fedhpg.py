"""FedHPG's local update: Algorithm 1, lines 5-8, for one agent.

θ^{k,0} ← θ̃_t
for τ = 0 … τ_k − 1:
    sample B_k trajectories from p_k(·|θ^{k,τ})
    θ^{k,τ+1} = θ^{k,τ} + η · (1/B_k) Σ_s g(l_s | θ^{k,τ})
return θ^{k,τ_k}
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from fedhpg.common.algorithms import (
    Algorithm,
    LocalContext,
    NoParams,
    at_least_one,
    register_algorithm,
)
from fedhpg.common.config import AlgoConfig
from fedhpg.common.estimators import clip_by_norm
from fedhpg.common.local import (
    IterationHook,
    LocalTally,
    SmoothnessProbe,
    TrajectorySource,
    apply_ascent,
    batch_gradient,
    bound_statistics,
)
from fedhpg.common.optim import make_optimizer
from fedhpg.common.policies import Policy, get_flat_params, set_flat_params
from fedhpg.common.types import LocalResult


@dataclass(frozen=True, kw_only=True)
class FedHPGBudget:
    """One agent's compute per round in Algorithm 1."""

    batch_size: int = 10
    """B_k: trajectories per local iteration."""
    local_iters: int = 2
    """τ_k: local iterations per round."""

    def __post_init__(self) -> None:
        at_least_one("batch_size", self.batch_size)
        at_least_one("local_iters", self.local_iters)


def fedhpg_local_update(
    theta: torch.Tensor,
    *,
    policy: Policy,
    sample: TrajectorySource,
    algo: AlgoConfig,
    gamma: float,
    batch_size: int,
    local_iters: int,
    on_iteration: IterationHook | None = None,
) -> LocalResult:
    """Run τ_k = ``local_iters`` policy-gradient ascent steps from the server's θ."""
    set_flat_params(policy, theta)
    optimizer = make_optimizer(algo)
    tally = LocalTally()
    probe = SmoothnessProbe()
    for iteration in range(local_iters):
        started = time.thread_time()
        batch = sample(batch_size)
        measuring = 0.0
        measure = algo.bound_estimates and iteration < 2
        if measure:  # at θ̃ (the constants) and one step on (the secant for L)
            begin = time.thread_time()
            found = bound_statistics(policy, batch, algo=algo, gamma=gamma)
            if iteration == 0:
                tally.algorithm.update(found)
            measuring = time.thread_time() - begin  # a diagnostic, not the device's work
        gradient = batch_gradient(policy, batch, algo=algo, gamma=gamma)
        if measure and found:
            probe.add(get_flat_params(policy), gradient, found["bound_variance"] / batch_size)
            tally.algorithm.update(probe.stats())
        gradient, clipped = clip_by_norm(gradient, algo.grad_clip)
        apply_ascent(policy, optimizer, gradient)
        compute_s = time.thread_time() - started - measuring
        tally.add(batch, compute_s=compute_s, clipped=clipped)
        if on_iteration is not None:
            on_iteration(iteration, compute_s, batch.num_steps)
    return tally.result(get_flat_params(policy))


@register_algorithm
class FedHPG(Algorithm[NoParams, FedHPGBudget]):
    """Algorithm 1: τ_k local policy-gradient steps on B_k trajectories each."""

    name = "fedhpg"
    Budget = FedHPGBudget

    def local_update(
        self, theta: torch.Tensor, context: LocalContext, params: NoParams, budget: FedHPGBudget
    ) -> LocalResult:
        return fedhpg_local_update(
            theta,
            policy=context.policy,
            sample=context.sample,
            algo=context.settings,
            gamma=context.gamma,
            batch_size=budget.batch_size,
            local_iters=budget.local_iters,
            on_iteration=context.on_iteration,
        )

    def describe_budget(self, budget: FedHPGBudget) -> str:
        return f"B={budget.batch_size} τ={budget.local_iters}"
