"""GymLoopBatchEnv: the same steps as gymnasium's SyncVectorEnv for every running copy, finished
copies never stepped again, deterministic in the seed; HalfCheetah without the MuJoCo warning."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from oracle import TrajectoryBatch, sample_trajectories

from fedhpg.common.learning.policies import PolicyConfig, make_policy
from fedhpg.envs.gym_adapter import GymLoopBatchEnv, GymVectorBatchEnv
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.registry import make_variants


def _variant(family: str) -> GymVariant:
    # Level 1: wind, action costs, edited physics, so the variant's settings are exercised.
    variant = make_variants(family, seed=0, num_agents=2, level=1.0)[1]
    assert isinstance(variant, GymVariant)
    return variant


def _sample(env, variant: GymVariant, seed: int, horizon: int) -> TrajectoryBatch:
    probe = variant.make_env()
    torch.manual_seed(0)
    policy = make_policy(probe.observation_space, probe.action_space, PolicyConfig(hidden=[16]))
    probe.close()
    return sample_trajectories(env, policy, np.random.default_rng(seed), horizon=horizon)


@pytest.mark.parametrize(
    ("family", "horizon"),
    [
        ("lunarlander", 1000),
        ("lunarlander-continuous", 1000),
        ("halfcheetah", 100),
        ("pendulum", 200),
        ("acrobot", 100),
    ],
)
def test_same_steps_as_sync_vector_env(family: str, horizon: int) -> None:
    variant = _variant(family)
    loop = variant.make_batch_env(6)
    assert isinstance(loop, GymLoopBatchEnv)
    sync = GymVectorBatchEnv(
        variant.env_id,
        6,
        env_kwargs=variant.env_kwargs,
        configure=variant.configure,
        action_cost=variant.action_cost,
    )
    ours, theirs = _sample(loop, variant, 3, horizon), _sample(sync, variant, 3, horizon)
    np.testing.assert_array_equal(ours.alive, theirs.alive)
    alive = ours.alive
    np.testing.assert_array_equal(ours.obs[alive], theirs.obs[alive])
    np.testing.assert_array_equal(ours.actions[alive], theirs.actions[alive])
    np.testing.assert_array_equal(ours.rewards, theirs.rewards)
    np.testing.assert_array_equal(ours.log_probs, theirs.log_probs)
    loop.close()
    sync.close()


def test_finished_copies_are_not_stepped() -> None:
    variant = _variant("lunarlander")
    env = variant.make_batch_env(8)
    calls = [0] * 8
    for i, copy in enumerate(env._envs):
        original = copy.step

        def counted(action, i=i, original=original):
            calls[i] += 1
            return original(action)

        copy.step = counted  # type: ignore[method-assign]
    batch = _sample(env, variant, 0, 1000)
    assert len(set(batch.lengths.tolist())) > 1, "episodes of different lengths"
    # LunarLander's reset() itself calls step() once to produce the first observation.
    stepped = [n - 1 for n in calls]
    assert stepped == batch.lengths.tolist(), "each copy stepped exactly for its own episode"
    env.close()


def test_same_seed_same_batch_other_seed_other_batch() -> None:
    variant = _variant("lunarlander-continuous")
    env = variant.make_batch_env(4)
    first, again = _sample(env, variant, 7, 1000), _sample(env, variant, 7, 1000)
    other = _sample(env, variant, 8, 1000)
    np.testing.assert_array_equal(first.obs, again.obs)
    np.testing.assert_array_equal(first.rewards, again.rewards)
    assert first.obs.shape != other.obs.shape or not np.array_equal(first.obs, other.obs)
    env.close()


def test_registered_step_limit_truncates() -> None:
    env = _variant("pendulum").make_batch_env(3)
    env.reset(seed=0)
    actions = np.zeros((3, 1), dtype=np.float32)
    for _ in range(199):
        step = env.step(actions)
        assert not (step.truncated.any() or step.terminated.any())
    step = env.step(actions)
    assert step.truncated.all() and not step.terminated.any(), "Pendulum-v1 stops at 200 steps"
    env.close()


def test_halfcheetah_compiles_without_the_deprecation_warning(capfd) -> None:
    env = make_variants("halfcheetah", seed=0, num_agents=1, level=0.0)[0].make_env()
    env.close()
    assert "settotalmass" not in capfd.readouterr().err


def test_halfcheetah_model_equals_the_stock_model() -> None:
    """Dropping settotalmass and calling mj_setTotalmass + mj_setConst gives the stock model:
    every numeric model array and a 300-step trajectory are identical."""
    ours = make_variants("halfcheetah", seed=0, num_agents=1, level=0.0)[0].make_env()
    stock = gym.make("HalfCheetah-v5", ctrl_cost_weight=0.1)
    a, b = ours.unwrapped.model, stock.unwrapped.model
    for name in dir(a):
        value = getattr(a, name, None)
        if not name.startswith("_") and isinstance(value, np.ndarray) and value.dtype.kind in "fi":
            np.testing.assert_array_equal(value, getattr(b, name), err_msg=name)
    rng = np.random.default_rng(0)
    obs_a, _ = ours.reset(seed=1)
    obs_b, _ = stock.reset(seed=1)
    for _ in range(300):
        action = rng.uniform(-1, 1, 6).astype(np.float32)
        obs_a, reward_a, *_ = ours.step(action)
        obs_b, reward_b, *_ = stock.step(action)
        np.testing.assert_array_equal(obs_a, obs_b)
        assert reward_a == reward_b
    ours.close()
    stock.close()
