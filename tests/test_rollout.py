"""The rollout sampler: masking after episode end, counting, one policy call per time step."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from fedhpg.common.policies import ActionSampler, MLPCategoricalPolicy, TabularSoftmaxPolicy
from fedhpg.common.rollout import sample_trajectories
from fedhpg.envs.base import BatchStep
from fedhpg.envs.gym_adapter import GymVectorBatchEnv


class CountdownEnv:
    """Copy b ends after b + 1 steps with reward 1 per step; afterwards it keeps emitting
    reward 100 so that any leak of post-episode steps into returns is visible."""

    def __init__(self, num_envs: int, *, truncate: bool = False) -> None:
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(4)
        self.single_action_space = gym.spaces.Discrete(2)
        self.truncate = truncate
        self.t = 0

    def reset(self, *, seed: int) -> np.ndarray:
        self.t = 0
        return np.zeros(self.num_envs, dtype=np.int64)

    def step(self, actions: np.ndarray) -> BatchStep:
        self.t += 1
        ends = np.arange(self.num_envs) + 1
        finished = self.t == ends
        after = self.t > ends
        return BatchStep(
            obs=np.full(self.num_envs, min(self.t, 3), dtype=np.int64),
            reward=np.where(after, 100.0, 1.0),
            terminated=finished & (not self.truncate),
            truncated=finished & self.truncate,
            success=finished,
        )

    def close(self) -> None:
        pass


@pytest.mark.parametrize("truncate", [False, True])
def test_steps_after_episode_end_neither_count_nor_leak(truncate: bool) -> None:
    env = CountdownEnv(4, truncate=truncate)
    policy = TabularSoftmaxPolicy(num_states=4, num_actions=2)
    batch = sample_trajectories(env, policy, np.random.default_rng(0), horizon=10)

    np.testing.assert_array_equal(batch.lengths, [1, 2, 3, 4])
    np.testing.assert_array_equal(batch.returns(), [1.0, 2.0, 3.0, 4.0])
    assert batch.num_steps == 10
    assert batch.num_trajectories == 4
    assert batch.obs.shape[0] == 4, "sampling stops once every copy is done"
    assert not batch.log_probs[~batch.alive].any()
    assert batch.success.all()


def test_horizon_cuts_episodes() -> None:
    batch = sample_trajectories(
        CountdownEnv(4),
        TabularSoftmaxPolicy(num_states=4, num_actions=2),
        np.random.default_rng(0),
        horizon=2,
    )
    np.testing.assert_array_equal(batch.lengths, [1, 2, 2, 2])
    assert batch.num_steps == 7
    np.testing.assert_array_equal(batch.success, [True, True, False, False])


def test_discounted_returns() -> None:
    batch = sample_trajectories(
        CountdownEnv(3),
        TabularSoftmaxPolicy(num_states=4, num_actions=2),
        np.random.default_rng(0),
        horizon=5,
    )
    np.testing.assert_allclose(batch.returns(0.5), [1.0, 1.5, 1.75])


def test_one_batched_policy_call_per_time_step() -> None:
    env = GymVectorBatchEnv("CartPole-v1", 16)
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=2)
    calls: list[int] = []
    original = policy.sampler

    def counting_sampler() -> ActionSampler:
        inner = original()

        def act(obs, rng, greedy):
            calls.append(obs.shape[0])
            return inner.act(obs, rng, greedy)

        return ActionSampler(act, inner.log_prob)

    policy.sampler = counting_sampler  # type: ignore[method-assign]
    batch = sample_trajectories(env, policy, np.random.default_rng(1), horizon=500)
    assert len(calls) == batch.obs.shape[0], "one call per time step"
    assert set(calls) == {16}, "each call covers all B copies"
    env.close()


def test_recorded_log_probs_match_policy() -> None:
    env = GymVectorBatchEnv("CartPole-v1", 8)
    torch.manual_seed(0)
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=2, hidden=[8])
    with torch.no_grad():
        policy.net[-1].weight.normal_()  # a non-uniform policy
    batch = sample_trajectories(env, policy, np.random.default_rng(2), horizon=50)
    with torch.no_grad():
        recomputed = policy.log_prob(torch.from_numpy(batch.obs), torch.from_numpy(batch.actions))
    np.testing.assert_allclose(
        batch.log_probs[batch.alive], recomputed.double().numpy()[batch.alive], atol=1e-5
    )
    env.close()


def test_same_seed_same_batch() -> None:
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=2)
    env = GymVectorBatchEnv("CartPole-v1", 8)
    first = sample_trajectories(env, policy, np.random.default_rng(3), horizon=100)
    second = sample_trajectories(env, policy, np.random.default_rng(3), horizon=100)
    np.testing.assert_array_equal(first.actions, second.actions)
    np.testing.assert_array_equal(first.rewards, second.rewards)
    env.close()


def test_bad_horizon_is_named() -> None:
    with pytest.raises(ValueError, match="horizon must be >= 1, got 0"):
        sample_trajectories(
            CountdownEnv(2),
            TabularSoftmaxPolicy(num_states=4, num_actions=2),
            np.random.default_rng(0),
            horizon=0,
        )
