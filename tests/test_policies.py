"""Policies: batched log-probabilities, samplers, flat parameter vectors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from fedhpg.common.learning.policies import (
    GaussianMLPPolicy,
    MLPCategoricalPolicy,
    PolicyConfig,
    TabularSoftmaxPolicy,
    get_flat_params,
    make_policy,
    set_flat_params,
)


def test_tabular_log_prob_matches_categorical() -> None:
    policy = TabularSoftmaxPolicy(num_states=5, num_actions=3)
    with torch.no_grad():
        policy.logits.normal_(generator=torch.Generator().manual_seed(0))
    obs = torch.tensor([[0, 4], [2, 2]])
    act = torch.tensor([[1, 0], [2, 1]])
    expected = torch.distributions.Categorical(logits=policy.logits[obs]).log_prob(act)
    torch.testing.assert_close(policy.log_prob(obs, act), expected)


def test_mlp_categorical_log_prob_matches_categorical() -> None:
    torch.manual_seed(0)
    policy = MLPCategoricalPolicy(obs_dim=3, num_actions=4, hidden=[8])
    obs = torch.randn(6, 2, 3)
    act = torch.randint(0, 4, (6, 2))
    expected = torch.distributions.Categorical(logits=policy.net(obs)).log_prob(act)
    torch.testing.assert_close(policy.log_prob(obs, act), expected)


@pytest.mark.parametrize("mode", ["state_independent", "state_dependent"])
def test_gaussian_log_prob_matches_normal(mode: str) -> None:
    torch.manual_seed(0)
    policy = GaussianMLPPolicy(obs_dim=3, act_dim=2, hidden=[8], log_std=mode)  # type: ignore[arg-type]
    obs = torch.randn(5, 3)
    act = torch.randn(5, 2)
    mean, log_std = policy._mean_and_log_std(obs)
    expected = torch.distributions.Normal(mean, log_std.exp()).log_prob(act).sum(-1)
    torch.testing.assert_close(policy.log_prob(obs, act), expected)


def test_tabular_draws_follow_the_policy() -> None:
    policy = TabularSoftmaxPolicy(num_states=2, num_actions=3)
    with torch.no_grad():
        policy.logits.copy_(torch.tensor([[0.0, 1.0, 2.0], [2.0, 0.0, -1.0]]))
    probs = torch.softmax(policy.logits, -1).detach().numpy()
    n = 200_000
    obs = np.repeat([0, 1], n // 2)
    noise = torch.from_numpy(np.random.default_rng(0).random((n, 1))).float()
    with torch.no_grad():
        actions = policy.act(torch.from_numpy(obs), noise).numpy()
    for state in (0, 1):
        freq = np.bincount(actions[obs == state], minlength=3) / (n // 2)
        stderr = np.sqrt(probs[state] * (1 - probs[state]) / (n // 2))
        assert np.all(np.abs(freq - probs[state]) < 4 * stderr)
    greedy = policy.act(torch.tensor([0, 1]), None)
    np.testing.assert_array_equal(greedy.numpy(), [2, 0])


def test_gaussian_draws_have_the_policys_moments() -> None:
    torch.manual_seed(0)
    policy = GaussianMLPPolicy(obs_dim=2, act_dim=1, hidden=[4], init_log_std=np.log(0.5))
    obs = torch.zeros(100_000, 2)
    noise = torch.from_numpy(np.random.default_rng(0).random((100_000, 1))).float()
    with torch.no_grad():
        actions = policy.act(obs, noise).numpy()
    mean = policy._mean_and_log_std(torch.zeros(1, 2))[0].item()
    assert abs(actions.mean() - mean) < 4 * 0.5 / np.sqrt(len(obs))
    # std of the sample std of n normals ≈ σ / sqrt(2n) = 0.0011: 0.005 is > 4 of those.
    assert abs(actions.std() - 0.5) < 0.005


def test_flat_params_round_trip_and_checks() -> None:
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=2, hidden=[16, 16])
    theta = get_flat_params(policy)
    assert theta.shape == (policy.num_params,) and theta.dtype == torch.float32
    new = torch.arange(theta.numel(), dtype=torch.float32)
    set_flat_params(policy, new)
    torch.testing.assert_close(get_flat_params(policy), new)
    with pytest.raises(ValueError, match=r"shape \(3,\), expected"):
        set_flat_params(policy, torch.zeros(3))
    bad = new.clone()
    bad[5] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        set_flat_params(policy, bad)


def test_make_policy_picks_by_spaces() -> None:
    config = PolicyConfig(hidden=[8])
    discrete = gym.spaces.Discrete(4)
    box = gym.spaces.Box(-1, 1, (3,))
    assert isinstance(make_policy(gym.spaces.Discrete(9), discrete, config), TabularSoftmaxPolicy)
    assert isinstance(make_policy(box, discrete, config), MLPCategoricalPolicy)
    assert isinstance(make_policy(box, gym.spaces.Box(-1, 1, (2,)), config), GaussianMLPPolicy)
    with pytest.raises(ValueError, match="unsupported observation space"):
        make_policy(gym.spaces.Box(-1, 1, (2, 2)), discrete, config)
