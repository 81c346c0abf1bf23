"""FedHPGVR's local update: Algorithm 2, lines 5-10, for one agent (SVRPG inside the round).

θ_0 ← θ̃_t
μ_k = (1/B_k) Σ_s g(l_s | θ_0),                  l_s ~ p_k(·|θ_0)
for n = 0 … N − 1:
    v_n = (1/b_k) Σ_j [g(l_j | θ_n) − w_j · g(l_j | θ_0)] + μ_k,   l_j ~ p_k(·|θ_n)
    θ_{n+1} = θ_n + η v_n
with w_j = p(l_j | θ_0) / p(l_j | θ_n)   (eq. 9 as SVRPG defines it; the paper prints θ_0 twice)
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Literal

import torch

from fedhpg.common.algorithms import Algorithm, LocalContext, at_least_one, register_algorithm
from fedhpg.common.config import AlgoConfig, ConfigError
from fedhpg.common.estimators import clip_by_norm
from fedhpg.common.importance import (
    clip_weights,
    log_ratio_steps,
    per_decision_weights,
    self_normalise,
    trajectory_weights,
)
from fedhpg.common.local import (
    IterationHook,
    LocalTally,
    TrajectorySource,
    apply_ascent,
    batch_gradient,
    batch_tensors,
)
from fedhpg.common.optim import make_optimizer
from fedhpg.common.policies import Policy, get_flat_params, set_flat_params
from fedhpg.common.registry import OptionError
from fedhpg.common.rollout import TrajectoryBatch
from fedhpg.common.types import LocalResult


@dataclass(frozen=True, kw_only=True)
class FedHPGVRParams:
    """FedHPGVR's importance weights w = p(τ|θ_0) / p(τ|θ_n) (``algo.params``)."""

    iw_mode: Literal["auto", "trajectory", "per_decision"] = "auto"
    """'trajectory' (one weight per trajectory), 'per_decision' (w_{0:h} per step, GPOMDP
    only), or 'auto': trajectory with REINFORCE, per-decision with GPOMDP."""
    iw_clip: tuple[float, float] | None = None
    """Clip the weights to [lo, hi]; None = off."""
    iw_self_normalize: bool = False
    """Divide the correction term by Σw instead of b_k."""

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
    return "trajectory" if algo.estimator == "reinforce" else "per_decision"


def importance_weights(
    snapshot: Policy,
    current: Policy,
    batch: TrajectoryBatch,
    algo: AlgoConfig,
    params: FedHPGVRParams,
) -> tuple[torch.Tensor, float]:
    """The weights the correction term uses ([B] or [T, B]) and the fraction clipped."""
    obs, actions = batch_tensors(batch)
    alive = torch.from_numpy(batch.alive)
    with torch.no_grad():
        log_ratios = log_ratio_steps(
            snapshot.log_prob(obs, actions), current.log_prob(obs, actions), alive
        )
    bounds = None if params.iw_clip is None else list(params.iw_clip)
    if importance_mode(params, algo) == "trajectory":
        weights, clipped = clip_weights(trajectory_weights(log_ratios), bounds)
    else:
        weights, clipped = clip_weights(per_decision_weights(log_ratios), bounds, alive)
    if params.iw_self_normalize:
        weights = self_normalise(weights)
    return weights, clipped


def semi_stochastic_gradient(
    current: Policy,
    snapshot: Policy,
    batch: TrajectoryBatch,
    snapshot_gradient: torch.Tensor,
    *,
    algo: AlgoConfig,
    params: FedHPGVRParams,
    gamma: float,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """v = (1/b) Σ_j [g(τ_j|θ_n) − w_j g(τ_j|θ_0)] + μ; also returns the weights used."""
    weights, clipped = importance_weights(snapshot, current, batch, algo, params)
    current_term = batch_gradient(current, batch, algo=algo, gamma=gamma)
    correction = batch_gradient(snapshot, batch, algo=algo, gamma=gamma, weights=weights)
    return current_term - correction + snapshot_gradient, weights, clipped


def fedhpgvr_local_update(
    theta: torch.Tensor,
    *,
    policy: Policy,
    sample: TrajectorySource,
    algo: AlgoConfig,
    params: FedHPGVRParams,
    gamma: float,
    batch_size: int,
    mini_batch_size: int,
    inner_steps: int,
    on_iteration: IterationHook | None = None,
) -> LocalResult:
    """Snapshot gradient from B_k trajectories, then N variance-reduced steps on b_k each."""
    set_flat_params(policy, theta)
    snapshot = copy.deepcopy(policy)
    tally = LocalTally()

    started = time.thread_time()
    snapshot_batch = sample(batch_size)
    mu = batch_gradient(snapshot, snapshot_batch, algo=algo, gamma=gamma)
    compute_s = time.thread_time() - started
    tally.add(snapshot_batch, compute_s=compute_s)
    if on_iteration is not None:
        on_iteration(0, compute_s, snapshot_batch.num_steps)

    optimizer = make_optimizer(algo)
    weight_sum = weight_count = clipped_total = 0.0
    weight_max = 0.0
    for step in range(inner_steps):
        started = time.thread_time()
        batch = sample(mini_batch_size)
        direction, weights, clipped = semi_stochastic_gradient(
            policy, snapshot, batch, mu, algo=algo, params=params, gamma=gamma
        )
        direction, was_clipped = clip_by_norm(direction, algo.grad_clip)
        apply_ascent(policy, optimizer, direction)
        compute_s = time.thread_time() - started
        tally.add(batch, compute_s=compute_s, clipped=was_clipped)
        final = weights if weights.ndim == 1 else weights[-1]
        weight_sum += float(final.sum())
        weight_count += final.numel()
        weight_max = max(weight_max, float(final.max()))
        clipped_total += clipped
        if on_iteration is not None:
            on_iteration(step + 1, compute_s, batch.num_steps)
    tally.algorithm.update(
        iw_mean=weight_sum / max(weight_count, 1.0),
        iw_max=weight_max,
        iw_clipped_fraction=clipped_total / max(inner_steps, 1),
    )
    return tally.result(get_flat_params(policy))


@register_algorithm
class FedHPGVR(Algorithm[FedHPGVRParams, FedHPGVRBudget]):
    """Algorithm 2: a snapshot gradient on B_k trajectories, N SVRPG steps on b_k each."""

    name = "fedhpgvr"
    Params = FedHPGVRParams
    Budget = FedHPGVRBudget

    def local_update(
        self,
        theta: torch.Tensor,
        context: LocalContext,
        params: FedHPGVRParams,
        budget: FedHPGVRBudget,
    ) -> LocalResult:
        return fedhpgvr_local_update(
            theta,
            policy=context.policy,
            sample=context.sample,
            algo=context.settings,
            params=params,
            gamma=context.gamma,
            batch_size=budget.batch_size,
            mini_batch_size=budget.mini_batch_size,
            inner_steps=budget.inner_steps,
            on_iteration=context.on_iteration,
        )

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
        if params.iw_mode == "per_decision" and settings.estimator == "reinforce":
            raise OptionError(
                "iw_mode",
                "per-decision weights need estimator 'gpomdp'; REINFORCE takes 'trajectory' "
                "or 'auto'",
            )

    def describe_budget(self, budget: FedHPGVRBudget) -> str:
        return f"B={budget.batch_size} b={budget.mini_batch_size} N={budget.inner_steps}"
