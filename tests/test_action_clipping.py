"""Gaussian actions are clipped to the action space's bounds before they reach the environment
and its action cost, in both batch envs and in ``make_env``; the sampler still records the raw
sample and its log-probability (the gradient is taken at the sample the policy drew).

Every pool, in-process or distributed, steps the same ``variant.make_batch_env`` through
``sample_trajectories``, so these checks cover both runtimes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from oracle import sample_trajectories

from fedhpg.common.learning.policies import GaussianMLPPolicy, PolicyConfig, make_policy
from fedhpg.envs.base import BatchEnv
from fedhpg.envs.gym_adapter import GymLoopBatchEnv, GymVectorBatchEnv
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.registry import make_variants

CONTINUOUS = ("pendulum", "lunarlander-continuous", "halfcheetah")
STEPS = 5


def _variant(family: str) -> GymVariant:
    # Level 1: every variant carries an action cost (Pendulum, LunarLander) or a control cost
    # weight of its own (HalfCheetah), so an unclipped action would be charged differently.
    variant = make_variants(family, seed=0, num_agents=2, level=1.0)[1]
    assert isinstance(variant, GymVariant)
    return variant


def _batch_envs(variant: GymVariant, num_envs: int) -> list[BatchEnv]:
    """Both implementations: the one the variant picks and gymnasium's vector env."""
    vector = GymVectorBatchEnv(
        variant.env_id,
        num_envs,
        env_kwargs=variant.env_kwargs,
        configure=variant.configure,
        action_cost=variant.action_cost,
    )
    return [variant.make_batch_env(num_envs), vector]


def _outside(space: gym.spaces.Box, num_envs: int) -> np.ndarray:
    """Actions far outside the box: +50 × the bound on copy 0, −50 × on the others."""
    scale = np.where(np.arange(num_envs) == 0, 50.0, -50.0)[:, None]
    return (scale * np.abs(space.high)[None, :]).astype(np.float32)


@pytest.mark.parametrize("family", CONTINUOUS)
def test_an_action_outside_the_bounds_reaches_the_env_clipped(family: str) -> None:
    """Stepping with out-of-bounds actions gives exactly the observations and rewards (action
    cost included) of stepping a fresh copy with the clipped actions."""
    variant = _variant(family)
    for raw_env, clipped_env in zip(_batch_envs(variant, 3), _batch_envs(variant, 3), strict=True):
        space = raw_env.single_action_space
        assert isinstance(space, gym.spaces.Box)
        raw = _outside(space, 3)
        clipped = np.clip(raw, space.low, space.high)
        assert not np.array_equal(raw, clipped)
        raw_env.reset(seed=7)
        clipped_env.reset(seed=7)
        for _ in range(STEPS):
            sent = raw.copy()
            a, b = raw_env.step(sent), clipped_env.step(clipped)
            np.testing.assert_array_equal(sent, raw, err_msg="the caller's actions are untouched")
            np.testing.assert_array_equal(a.obs, b.obs)
            np.testing.assert_array_equal(a.reward, b.reward)
            # the charge is bounded by the cost of a valid action: −c·‖clip(a)‖² at worst
            assert np.all(np.isfinite(a.reward))
        raw_env.close()
        clipped_env.close()


@pytest.mark.parametrize("family", CONTINUOUS)
def test_make_env_clips_too(family: str) -> None:
    variant = _variant(family)
    raw_env, clipped_env = variant.make_env(), variant.make_env()
    space = raw_env.action_space
    assert isinstance(space, gym.spaces.Box)
    raw = _outside(space, 1)[0]
    raw_env.reset(seed=3)
    clipped_env.reset(seed=3)
    for _ in range(STEPS):
        a = raw_env.step(raw)
        b = clipped_env.step(np.clip(raw, space.low, space.high))
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1] == b[1]
    raw_env.close()
    clipped_env.close()


def test_the_unclipped_action_cost_would_differ() -> None:
    """The check above can fail: charged on the raw action, HalfCheetah's control cost (weight
    ≈ 0.1 per unit²) of a ±50 action would be ~250 per joint and step, not ≤ 0.6 in all."""
    variant = _variant("halfcheetah")
    env = gym.make(variant.env_id, **variant.env_kwargs).unwrapped  # no clipping wrapper
    env.reset(seed=3)
    raw = _outside(env.action_space, 1)[0]
    _, reward, *_ = env.step(raw)
    assert reward < -100.0
    env.close()


@pytest.mark.parametrize("family", CONTINUOUS)
def test_the_log_probability_is_that_of_the_raw_sample(family: str) -> None:
    """A policy whose mean sits at 10 × the upper bound: the batch records the raw samples
    (mostly outside the box) and log π of those, while the env saw them clipped."""
    variant = _variant(family)
    probe = variant.make_env()
    space = probe.action_space
    assert isinstance(space, gym.spaces.Box)
    torch.manual_seed(0)
    policy = make_policy(probe.observation_space, space, PolicyConfig(hidden=[8]))
    probe.close()
    assert isinstance(policy, GaussianMLPPolicy)
    with torch.no_grad():
        policy.mean_net[-1].bias.copy_(torch.as_tensor(10.0 * space.high))
    env = variant.make_batch_env(4)
    assert isinstance(env, GymLoopBatchEnv | GymVectorBatchEnv)
    batch = sample_trajectories(env, policy, np.random.default_rng(1), horizon=20)
    env.close()
    alive = batch.alive
    actions = batch.actions[alive]
    assert (actions > space.high).mean() > 0.9, "the recorded actions are the raw samples"
    with torch.no_grad():
        expected = policy.log_prob(
            torch.as_tensor(batch.obs[alive]), torch.as_tensor(actions)
        ).numpy()
    np.testing.assert_allclose(batch.log_probs[alive], expected, rtol=1e-5, atol=1e-4)
    clipped = np.clip(actions, space.low, space.high)
    with torch.no_grad():
        at_clipped = policy.log_prob(
            torch.as_tensor(batch.obs[alive]), torch.as_tensor(clipped)
        ).numpy()
    assert not np.allclose(batch.log_probs[alive], at_clipped), "not the clipped action's"
