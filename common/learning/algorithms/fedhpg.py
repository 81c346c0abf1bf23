"""FedHPG's local update: Algorithm 1, lines 5-8, for every agent of the batch at once.

θ^{k,0} ← θ̃_t
for τ = 0 … τ_k − 1:
    sample B_k trajectories from p_k(·|θ^{k,τ})
    θ^{k,τ+1} = θ^{k,τ} + η · (1/B_k) Σ_s g(l_s | θ^{k,τ})
return θ^{k,τ_k}

Rows whose τ_k is spent sit out the later iterations (they sample nothing and do not move).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.learning.algorithms import Algorithm, NoParams, at_least_one, register_algorithm
from fedhpg.common.learning.bounds import row_bound_statistics
from fedhpg.common.learning.engine.round import Round
from fedhpg.common.learning.estimators import clip_rows
from fedhpg.common.learning.optim import make_optimizer


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


@register_algorithm
class FedHPG(Algorithm[NoParams, FedHPGBudget]):
    """Algorithm 1: τ_k local policy-gradient steps on B_k trajectories each."""

    name = "fedhpg"
    Budget = FedHPGBudget
    theorem1 = True

    def local_update(self, rows: Round, settings: AlgoConfig, params: NoParams) -> torch.Tensor:
        algo = settings
        theta = rows.theta.clone()
        ascent = make_optimizer(algo)
        local_iters, batch_size = rows.budget("local_iters"), rows.budget("batch_size")
        bounds = row_bound_statistics(rows.size) if algo.bound_estimates else None
        fewest, most = rows.budget_span("local_iters")
        for iteration in range(most):
            if iteration < fewest:  # every row runs
                counts, active = batch_size, None
            else:
                active = local_iters > iteration
                counts = torch.where(active, batch_size, 0)
            batch = rows.sample(theta, counts, iteration=iteration)
            gradient = rows.mean_gradients(theta, batch)
            if bounds is not None and iteration < 2:  # at θ̃, and the secant for L
                bounds.measure(rows, theta, batch, gradient, first=iteration == 0)
            gradient, clipped = clip_rows(gradient, algo.grad_clip)
            theta += ascent.direction(gradient, None if active is None else active.to(theta.device))
            rows.finished(batch, clipped=clipped)
            del batch  # its memory goes back to the sampler (one batch held at a time)
        if bounds is not None:
            bounds.report(rows)
        return theta

    def held_trajectories(self, budget: FedHPGBudget) -> int:
        return budget.batch_size  # one iteration's batch at a time

    def describe_budget(self, budget: FedHPGBudget) -> str:
        return f"B={budget.batch_size} τ={budget.local_iters}"
