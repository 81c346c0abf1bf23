"""FedHPGVR on the exact tabular MDP: importance weights are the true trajectory-probability
ratios, the semi-stochastic gradient v is unbiased for ∇J(θ_n), and near the snapshot it has
less variance than plain GPOMDP on the same number of fresh trajectories."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from exact_mdp import (
    Z_LIMIT,
    exact_gradient,
    make_policy,
    max_standard_errors,
    sample,
    trajectory_log_probability,
)

from fedhpg.common.algorithms.fedhpgvr import FedHPGVRParams, importance_weights
from fedhpg.common.config import AlgoConfig
from fedhpg.common.estimators import estimator_coefficients, per_trajectory_gradients
from fedhpg.common.policies import TabularSoftmaxPolicy
from fedhpg.common.rollout import TrajectoryBatch

GAMMA = 0.9
DRAWS = 3000
SNAPSHOT_BATCH = 16  # B_k
MINI_BATCH = 4  # b_k


def _moved(policy: TabularSoftmaxPolicy, scale: float, seed: int) -> TabularSoftmaxPolicy:
    moved = copy.deepcopy(policy)
    with torch.no_grad():
        moved.logits.add_(
            scale * torch.randn(moved.logits.shape, generator=torch.Generator().manual_seed(seed))
        )
    return moved


def _group_gradients(
    policy: TabularSoftmaxPolicy,
    batch: TrajectoryBatch,
    group: int,
    algo: AlgoConfig,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """[G, d]: (1/group) Σ_j w_j g(τ_j | θ) for consecutive groups of trajectories."""
    rewards, alive = torch.from_numpy(batch.rewards), torch.from_numpy(batch.alive)
    parts = []
    for start in range(0, rewards.shape[1], group):
        cols = slice(start, start + group)
        w = None if weights is None else weights[..., cols]
        parts.append(
            estimator_coefficients(
                algo.estimator,
                rewards[:, cols],
                alive[:, cols],
                gamma=GAMMA,  # type: ignore[arg-type]
                baseline=algo.baseline,
                weights=w,  # type: ignore[arg-type]
            )
        )
    obs, actions = torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)
    rows = per_trajectory_gradients(policy, obs, actions, torch.cat(parts, dim=1)).double()
    return rows.reshape(-1, group, rows.shape[1]).mean(dim=1)


def _v_draws(
    algo: AlgoConfig,
    params: FedHPGVRParams,
    snapshot: TabularSoftmaxPolicy,
    current: TabularSoftmaxPolicy,
    seed: int,
) -> torch.Tensor:
    """DRAWS independent semi-stochastic gradients v = mean_j[g_n − w g_0] + μ."""
    mu = _group_gradients(
        snapshot, sample(snapshot, DRAWS * SNAPSHOT_BATCH, seed), SNAPSHOT_BATCH, algo
    )
    fresh = sample(current, DRAWS * MINI_BATCH, seed + 1)
    weights, _ = importance_weights(snapshot, current, fresh, algo, params)
    current_term = _group_gradients(current, fresh, MINI_BATCH, algo)
    correction = _group_gradients(snapshot, fresh, MINI_BATCH, algo, weights=weights)
    return current_term - correction + mu


def test_weights_are_the_exact_trajectory_probability_ratio() -> None:
    snapshot = make_policy(seed=0)
    current = _moved(snapshot, 0.5, seed=1)
    batch = sample(current, 256, seed=2)
    algo = AlgoConfig(name="fedhpgvr", estimator="reinforce")
    weights, _ = importance_weights(
        snapshot, current, batch, algo, FedHPGVRParams(iw_mode="trajectory")
    )
    exact = np.exp(
        trajectory_log_probability(snapshot.logits, batch.obs, batch.actions, batch.alive)
        - trajectory_log_probability(current.logits, batch.obs, batch.actions, batch.alive)
    )
    np.testing.assert_allclose(weights.numpy(), exact, rtol=1e-5)
    assert np.ptp(exact) > 0.5, "the policies differ enough for the weights to matter"

    per_decision, _ = importance_weights(
        snapshot,
        current,
        batch,
        AlgoConfig(name="fedhpgvr"),
        FedHPGVRParams(iw_mode="per_decision"),
    )
    np.testing.assert_allclose(per_decision[-1].numpy(), exact, rtol=1e-5)  # w_{0:H-1} = w(τ)
    assert per_decision.shape == (batch.obs.shape[0], 256)


@pytest.mark.parametrize(
    ("estimator", "mode"), [("reinforce", "trajectory"), ("gpomdp", "per_decision")]
)
def test_v_is_unbiased_for_the_gradient_at_theta_n(estimator: str, mode: str) -> None:
    snapshot = make_policy(seed=0)
    current = _moved(snapshot, 0.5, seed=1)
    algo = AlgoConfig(name="fedhpgvr", estimator=estimator, baseline="none")
    params = FedHPGVRParams(iw_mode=mode)  # type: ignore[arg-type]
    draws = _v_draws(algo, params, snapshot, current, seed=10)
    exact_current = exact_gradient(current.logits, GAMMA)
    z = max_standard_errors(draws, exact_current)
    assert z < Z_LIMIT, f"{estimator}/{mode}: E[v] is {z:.2f} standard errors from ∇J(θ_n)"
    # ... and not merely close to the snapshot's gradient: the test can tell them apart.
    assert max_standard_errors(draws, exact_gradient(snapshot.logits, GAMMA)) > Z_LIMIT


def test_near_the_snapshot_v_has_less_variance_than_plain_gpomdp() -> None:
    snapshot = make_policy(seed=0)
    current = _moved(snapshot, 0.05, seed=1)
    algo = AlgoConfig(name="fedhpgvr", estimator="gpomdp")
    v = _v_draws(algo, FedHPGVRParams(iw_mode="per_decision"), snapshot, current, seed=20)
    plain = _group_gradients(
        current, sample(current, DRAWS * MINI_BATCH, seed=30), MINI_BATCH, algo
    )
    variance_v, variance_plain = float(v.var(0).sum()), float(plain.var(0).sum())
    assert variance_v < variance_plain, (variance_v, variance_plain)
