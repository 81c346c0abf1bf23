"""FedHPGVR's local update: Algorithm 2, lines 5-10, for every agent of the batch at once
(SVRPG inside the round).

θ_0 ← θ̃_t
μ_k = (1/B_k) Σ_s g(l_s | θ_0),                  l_s ~ p_k(·|θ_0)
for n = 0 … N − 1:
    v_n = (1/b_k) Σ_j [g(l_j | θ_n) − w_j · g(l_j | θ_0)] + μ_k,   l_j ~ p_k(·|θ_n)
    θ_{n+1} = θ_n + η v_n
with w_j = p(l_j | θ_0) / p(l_j | θ_n)   (eq. 9 as SVRPG defines it; the paper prints θ_0 twice)

Rows whose N is spent sit out the later inner steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import OptionError
from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.configuration.vocabularies import ESTIMATORS
from fedhpg.common.learning.algorithms import Algorithm, at_least_one, register_algorithm
from fedhpg.common.learning.engine.round import Round
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.estimators import clip_rows
from fedhpg.common.learning.importance import (
    log_ratio_steps,
    per_decision_weights,
    self_normalise,
    trajectory_weights,
)
from fedhpg.common.learning.optim import make_optimizer


@dataclass(frozen=True, kw_only=True)
class FedHPGVRParams:
    """FedHPGVR's importance weights w = p(τ|θ_0) / p(τ|θ_n) (``algo.params``)."""

    iw_mode: Literal["auto", "trajectory", "per_decision"] = "auto"
    """'trajectory' (one weight per trajectory), 'per_decision' (w_{0:h} per step, GPOMDP
    only), or 'auto': trajectory with REINFORCE, per-decision with GPOMDP."""
    iw_clip: tuple[float, float] | None = None
    """Clip the weights to [lo, hi]; None = off. The correction term, and so the gradient
    estimate, is then biased for ∇J."""
    iw_self_normalize: bool = False
    """Divide the correction term by Σw instead of b_k. The estimate is then biased for ∇J, by
    an amount that shrinks about as 1/b_k."""

    def __post_init__(self) -> None:
        if self.iw_clip is not None:
            if len(self.iw_clip) != 2:
                raise OptionError("iw_clip", f"needs two bounds [lo, hi], got {self.iw_clip!r}")
            lo, hi = self.iw_clip
            if not 0.0 <= lo <= hi or hi <= 0.0:
                raise OptionError("iw_clip", f"needs 0 <= lo <= hi, hi > 0, got {self.iw_clip!r}")


@dataclass(frozen=True, kw_only=True)
class FedHPGVRBudget:
    """One agent's compute per round in Algorithm 2."""

    batch_size: int = 10
    """B_k: trajectories of the snapshot gradient μ_k."""
    inner_steps: int = 3
    """N: variance-reduced inner steps per round."""
    mini_batch_size: int = 5
    """b_k: trajectories per inner step."""

    def __post_init__(self) -> None:
        at_least_one("batch_size", self.batch_size)
        at_least_one("inner_steps", self.inner_steps)
        at_least_one("mini_batch_size", self.mini_batch_size)


def importance_mode(params: FedHPGVRParams, algo: AlgoConfig) -> str:
    """'trajectory' weights pair with REINFORCE, per-decision weights with GPOMDP."""
    if params.iw_mode != "auto":
        return params.iw_mode
    return "per_decision" if ESTIMATORS.get(algo.estimator).per_step else "trajectory"


@dataclass(frozen=True)
class Weights:
    """The importance weights of a batch and what the statistics report of them."""

    values: torch.Tensor
    """[N] (per trajectory) or [T, N] (per decision)."""
    final: torch.Tensor
    """Each trajectory's weight over its whole length, [N]."""
    clipped: torch.Tensor
    """Per row: the fraction of its weights the clip changed, [A]."""


def importance_weights(
    rows: Round,
    settings: AlgoConfig,
    theta_n: torch.Tensor,
    theta_0: torch.Tensor,
    batch: Trajectories,
    params: FedHPGVRParams,
) -> Weights:
    """w = p(τ|θ_0) / p(τ|θ_n) for every trajectory of ``batch`` (drawn at θ_n), each row at
    its own two θ rows; clipped and self-normalised as ``params`` say."""
    log_ratios = log_ratio_steps(
        rows.log_probs(theta_0, batch), rows.log_probs(theta_n, batch), batch.alive
    )
    per_decision = importance_mode(params, settings) == "per_decision"
    weights = per_decision_weights(log_ratios) if per_decision else trajectory_weights(log_ratios)
    counted = batch.alive if per_decision else torch.ones_like(weights, dtype=torch.bool)
    changed = torch.zeros_like(weights, dtype=torch.bool)
    if params.iw_clip is not None:
        low, high = params.iw_clip
        clipped = weights.clamp(min=low, max=high)
        changed = clipped != weights
        weights = clipped
    cells = counted.reshape(-1, counted.shape[-1]).sum(dim=0).double()
    changes = (changed & counted).reshape(-1, counted.shape[-1]).sum(dim=0).double()
    fraction = batch.per_row(changes) / batch.per_row(cells).clamp_min(1.0)
    if params.iw_self_normalize:
        weights = self_normalise(weights, batch.owner)
    final = weights if weights.dim() == 1 else _last_alive(weights, batch.alive)
    return Weights(values=weights, final=final, clipped=fraction)


def _last_alive(weights: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
    """Each column's weight at its last alive step (the weight of the whole trajectory)."""
    last = (alive.sum(dim=0) - 1).clamp_min(0)
    return weights.gather(0, last.unsqueeze(0)).squeeze(0)


def semi_stochastic_gradient(
    rows: Round,
    settings: AlgoConfig,
    theta_n: torch.Tensor,
    theta_0: torch.Tensor,
    batch: Trajectories,
    mu: torch.Tensor,
    params: FedHPGVRParams,
) -> tuple[torch.Tensor, Weights]:
    """v = (1/b) Σ_j [g(τ_j|θ_n) − w_j g(τ_j|θ_0)] + μ per row; also the weights used."""
    weights = importance_weights(rows, settings, theta_n, theta_0, batch, params)
    current = rows.mean_gradients(theta_n, batch)
    correction = rows.mean_gradients(theta_0, batch, weights.values)
    return current - correction + mu, weights


@register_algorithm
class FedHPGVR(Algorithm[FedHPGVRParams, FedHPGVRBudget]):
    """Algorithm 2: a snapshot gradient on B_k trajectories, N SVRPG steps on b_k each."""

    name = "fedhpgvr"
    Params = FedHPGVRParams
    Budget = FedHPGVRBudget

    def local_update(
        self, rows: Round, settings: AlgoConfig, params: FedHPGVRParams
    ) -> torch.Tensor:
        algo = settings
        theta_0 = rows.theta
        snapshot = rows.sample(theta_0, rows.budget("batch_size"), iteration=0)
        mu = rows.mean_gradients(theta_0, snapshot)
        rows.finished(snapshot)
        del snapshot  # its memory goes back to the sampler (one batch held at a time)
        theta = theta_0.clone()
        ascent = make_optimizer(algo)
        inner_steps, mini_batch = rows.budget("inner_steps"), rows.budget("mini_batch_size")
        # the weights' statistics stay where the rows are until the round reports them
        weight_sum, weight_max, clipped_sum = theta.new_zeros((3, rows.size), dtype=torch.float64)
        for step in range(rows.budget_span("inner_steps")[1]):
            active = inner_steps > step
            batch = rows.sample(theta, torch.where(active, mini_batch, 0), iteration=step + 1)
            direction, weights = semi_stochastic_gradient(
                rows, algo, theta, theta_0, batch, mu, params
            )
            direction, clipped = clip_rows(direction, algo.grad_clip)
            theta += ascent.direction(direction, active.to(theta.device))
            rows.finished(batch, clipped=clipped, grad_steps=2 * batch.steps_per_row())
            final = weights.final.double()
            weight_sum += batch.per_row(final)
            weight_max = torch.maximum(
                weight_max,
                torch.zeros_like(weight_max).scatter_reduce(
                    0, batch.owner, final, "amax", include_self=False
                ),
            )
            clipped_sum += weights.clipped
            del batch, weights  # back to the sampler before the next step's batch
        trajectories = (inner_steps * mini_batch).double().to(theta.device)
        rows.report("iw_mean", weight_sum / trajectories)
        rows.report("iw_max", weight_max)
        rows.report("iw_clipped_fraction", clipped_sum / inner_steps.double().to(theta.device))
        return theta

    def check(self, settings: AlgoConfig, params: FedHPGVRParams) -> None:
        # The practice options stay with FedHPG: standardising would rescale the snapshot
        # gradient and the importance-weighted correction by different batches' spreads, so
        # the two no longer cancel; from_step's weighted correction is not checked against an
        # exact expectation (tests/test_fedhpgvr_exact.py covers eq. 5/6 only).
        for key, value, paper in (
            ("reward_to_go", settings.reward_to_go, "from_start"),
            ("normalize", settings.normalize, "none"),
        ):
            if value != paper:
                raise ConfigError(
                    f"algo.{key}",
                    f"FedHPGVR takes {paper!r} only (the paper's estimators), got {value!r}",
                )
        if params.iw_mode == "per_decision" and not ESTIMATORS.get(settings.estimator).per_step:
            raise OptionError(
                "iw_mode",
                "per-decision weights need estimator 'gpomdp'; REINFORCE takes 'trajectory' "
                "or 'auto'",
            )

    def held_trajectories(self, budget: FedHPGVRBudget) -> int:
        return budget.batch_size + budget.mini_batch_size  # the snapshot's and one inner batch

    def describe_budget(self, budget: FedHPGVRBudget) -> str:
        return f"B={budget.batch_size} b={budget.mini_batch_size} N={budget.inner_steps}"
