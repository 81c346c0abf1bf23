"""FedHPGVR (Algorithm 2): importance weights and the semi-stochastic gradient."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from fedhpg.common.algorithms.fedhpgvr import (
    FedHPGVRParams,
    importance_weights,
    semi_stochastic_gradient,
)
from fedhpg.common.config import AlgoConfig
from fedhpg.common.importance import clip_weights, self_normalise
from fedhpg.common.local import batch_gradient
from fedhpg.common.policies import MLPCategoricalPolicy
from fedhpg.common.rollout import sample_trajectories
from fedhpg.envs.gym_adapter import GymVectorBatchEnv


@pytest.fixture(scope="module")
def cartpole_batch():
    torch.manual_seed(0)
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=2, hidden=[16])
    env = GymVectorBatchEnv("CartPole-v1", 8)
    batch = sample_trajectories(env, policy, np.random.default_rng(0), horizon=200)
    env.close()
    return policy, batch


@pytest.mark.parametrize(
    ("estimator", "mode"),
    [("reinforce", "trajectory"), ("gpomdp", "per_decision"), ("gpomdp", "trajectory")],
)
def test_at_the_snapshot_weights_are_one_and_v_is_mu(cartpole_batch, estimator, mode) -> None:
    policy, batch = cartpole_batch
    snapshot = copy.deepcopy(policy)
    algo = AlgoConfig(name="fedhpgvr", estimator=estimator)
    params = FedHPGVRParams(iw_mode=mode)  # type: ignore[arg-type]
    weights, clipped = importance_weights(snapshot, policy, batch, algo, params)
    assert torch.equal(weights, torch.ones_like(weights)), "θ_n = θ_0 ⇒ every w is exactly 1"
    assert clipped == 0.0
    mu = torch.randn(policy.num_params, generator=torch.Generator().manual_seed(1))
    v, _, _ = semi_stochastic_gradient(
        policy, snapshot, batch, mu, algo=algo, params=params, gamma=0.99
    )
    # g(τ|θ_n) − 1·g(τ|θ_0) vanishes term by term when θ_n = θ_0.
    torch.testing.assert_close(v, mu, atol=1e-6, rtol=0)


def test_weights_move_away_from_one_off_the_snapshot(cartpole_batch) -> None:
    policy, batch = cartpole_batch
    snapshot = copy.deepcopy(policy)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    algo = AlgoConfig(name="fedhpgvr", estimator="reinforce")
    weights, _ = importance_weights(snapshot, policy, batch, algo, FedHPGVRParams())
    obs, act = torch.from_numpy(batch.obs), torch.from_numpy(batch.actions)
    alive = torch.from_numpy(batch.alive)
    with torch.no_grad():
        log_ratio = (snapshot.log_prob(obs, act) - policy.log_prob(obs, act)).double()
    expected = torch.where(alive, log_ratio, 0.0).sum(0).exp()
    torch.testing.assert_close(weights, expected)
    assert not torch.allclose(weights, torch.ones_like(weights))


def test_clip_and_self_normalise() -> None:
    weights = torch.tensor([0.1, 1.0, 5.0, 2.0], dtype=torch.float64)
    clipped, fraction = clip_weights(weights, [0.5, 2.0])
    torch.testing.assert_close(clipped, torch.tensor([0.5, 1.0, 2.0, 2.0], dtype=torch.float64))
    assert fraction == 0.5
    normalised = self_normalise(weights)
    torch.testing.assert_close(normalised.mean(), torch.tensor(1.0, dtype=torch.float64))
    per_step = self_normalise(torch.tensor([[1.0, 3.0], [2.0, 2.0]], dtype=torch.float64))
    torch.testing.assert_close(per_step.mean(dim=-1), torch.ones(2, dtype=torch.float64))


def test_self_normalised_correction_is_a_weighted_mean(cartpole_batch) -> None:
    policy, batch = cartpole_batch
    algo = AlgoConfig(name="fedhpgvr", estimator="reinforce")
    weights = torch.tensor([0.5, 1.5, 1.0, 2.0, 0.2, 0.3, 0.4, 2.1], dtype=torch.float64)
    scaled = batch_gradient(policy, batch, algo=algo, gamma=0.99, weights=self_normalise(weights))
    unnormalised = batch_gradient(policy, batch, algo=algo, gamma=0.99, weights=weights)
    # (1/b) Σ (b w_j / Σw) g_j = Σ w_j g_j / Σ w_j = (b / Σw) · (1/b) Σ w_j g_j
    torch.testing.assert_close(
        scaled, unnormalised * (8 / weights.sum()).float(), atol=1e-5, rtol=1e-4
    )
