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

import torch

from fedhpg.common.config import AlgoConfig
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
    LocalResult,
    LocalTally,
    TrajectorySource,
    apply_ascent,
    batch_gradient,
    batch_tensors,
    make_optimizer,
)
from fedhpg.common.policies import Policy, get_flat_params, set_flat_params
from fedhpg.common.rollout import TrajectoryBatch


def importance_mode(algo: AlgoConfig) -> str:
    """'trajectory' weights pair with REINFORCE, per-decision weights with GPOMDP."""
    if algo.iw_mode != "auto":
        return algo.iw_mode
    return "trajectory" if algo.estimator == "reinforce" else "per_decision"


def importance_weights(
    snapshot: Policy, current: Policy, batch: TrajectoryBatch, algo: AlgoConfig
) -> tuple[torch.Tensor, float]:
    """The weights the correction term uses ([B] or [T, B]) and the fraction clipped."""
    obs, actions = batch_tensors(batch)
    alive = torch.from_numpy(batch.alive)
    with torch.no_grad():
        log_ratios = log_ratio_steps(
            snapshot.log_prob(obs, actions), current.log_prob(obs, actions), alive
        )
    if importance_mode(algo) == "trajectory":
        weights, clipped = clip_weights(trajectory_weights(log_ratios), algo.iw_clip)
    else:
        weights, clipped = clip_weights(per_decision_weights(log_ratios), algo.iw_clip, alive)
    if algo.iw_self_normalize:
        weights = self_normalise(weights)
    return weights, clipped


def semi_stochastic_gradient(
    current: Policy,
    snapshot: Policy,
    batch: TrajectoryBatch,
    snapshot_gradient: torch.Tensor,
    *,
    algo: AlgoConfig,
    gamma: float,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """v = (1/b) Σ_j [g(τ_j|θ_n) − w_j g(τ_j|θ_0)] + μ; also returns the weights used."""
    weights, clipped = importance_weights(snapshot, current, batch, algo)
    current_term = batch_gradient(current, batch, algo=algo, gamma=gamma)
    correction = batch_gradient(snapshot, batch, algo=algo, gamma=gamma, weights=weights)
    return current_term - correction + snapshot_gradient, weights, clipped


def fedhpgvr_local_update(
    theta: torch.Tensor,
    *,
    policy: Policy,
    sample: TrajectorySource,
    algo: AlgoConfig,
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
            policy, snapshot, batch, mu, algo=algo, gamma=gamma
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
    tally.extra.update(
        iw_mean=weight_sum / max(weight_count, 1.0),
        iw_max=weight_max,
        iw_clipped_fraction=clipped_total / max(inner_steps, 1),
    )
    return tally.result(get_flat_params(policy))
