"""Heterogeneous gymnasium families: real differences, reproducible, same spaces, valid envs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fedhpg.envs.families import GYM_FAMILIES
from fedhpg.envs.registry import make_variants

FAMILIES = sorted(GYM_FAMILIES)


@pytest.mark.parametrize("family", FAMILIES)
def test_variants_differ_share_spaces_and_reproduce(family: str) -> None:
    variants = make_variants(family, seed=0, num_agents=3, level=1.0)
    assert len({str(v.params) for v in variants}) == 3, "three distinct variants"
    assert len({str(v.signature()) for v in variants}) == 1, "identical spaces"
    assert [v.params for v in variants] == [
        v.params for v in make_variants(family, seed=0, num_agents=3, level=1.0)
    ]
    assert [v.params for v in variants] != [
        v.params for v in make_variants(family, seed=1, num_agents=3, level=1.0)
    ]
    stock = make_variants(family, seed=0, num_agents=3, level=0.0)
    assert len({str(v.params) for v in stock}) == 1, "level 0: identical copies"


@pytest.mark.parametrize("family", FAMILIES)
def test_variant_env_passes_check_env(family: str) -> None:
    env = make_variants(family, seed=0, num_agents=2, level=1.0)[1].make_env()
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("family", FAMILIES)
def test_heterogeneity_changes_the_dynamics(family: str) -> None:
    """Same seed, same actions: two variants' observation or reward streams differ."""
    variants = make_variants(family, seed=0, num_agents=2, level=1.0)
    streams = []
    for variant in variants:
        env = variant.make_batch_env(2)
        obs = [env.reset(seed=3)]
        space = env.single_action_space
        rng = np.random.default_rng(0)
        rewards = []
        for _ in range(15):
            if hasattr(space, "n"):
                actions = rng.integers(0, space.n, size=2)
            else:
                actions = rng.uniform(space.low, space.high, size=(2, *space.shape)).astype(
                    np.float32
                )
            step = env.step(actions)
            obs.append(step.obs)
            rewards.append(step.reward)
        env.close()
        streams.append((np.concatenate([np.ravel(o) for o in obs]), np.ravel(rewards)))
    (obs_a, rew_a), (obs_b, rew_b) = streams
    assert not (np.allclose(obs_a, obs_b) and np.allclose(rew_a, rew_b))


def test_the_batched_env_gets_the_variant_physics() -> None:
    variant = make_variants("cartpole", seed=0, num_agents=2, level=1.0)[1]
    env = variant.make_batch_env(4)
    vector = env._env.unwrapped
    assert vector.length == pytest.approx(variant.params["length"], abs=1e-4)
    assert vector.polemass_length == pytest.approx(vector.masspole * vector.length)
    env.close()
    cheetah = make_variants("halfcheetah", seed=0, num_agents=2, level=1.0)[1]
    stock = make_variants("halfcheetah", seed=0, num_agents=2, level=0.0)[1]
    edited, plain = cheetah.make_env().unwrapped, stock.make_env().unwrapped
    ratio = edited.model.opt.gravity[2] / plain.model.opt.gravity[2]
    assert ratio == pytest.approx(cheetah.params["gravity_scale"], abs=1e-4)


def test_action_cost_is_charged() -> None:
    """reward = the task's reward − c·‖a‖², in the batched env and the single env alike."""
    variant = make_variants("pendulum", seed=0, num_agents=1, level=1.0)[0]
    free = dataclasses.replace(variant, action_cost=0.0)
    action = np.array([[1.5]], dtype=np.float32)
    rewards = []
    for v in (variant, free):
        env = v.make_batch_env(1)
        env.reset(seed=0)
        rewards.append(float(env.step(action).reward[0]))
        env.close()
    assert rewards[0] - rewards[1] == pytest.approx(-variant.action_cost * 1.5**2)
    single = variant.make_env()
    single.reset(seed=0)
    charged = single.step(action[0])[1]
    single.close()
    assert charged == pytest.approx(rewards[0])


@pytest.mark.parametrize(
    ("family", "kwargs", "message"),
    [
        ("mujoco-ant", {}, "unknown environment family 'mujoco-ant'; known: acrobot, cartpole"),
        ("cartpole", {"level": 1.5}, r"level must be in \[0, 1\], got 1.5"),
        ("lunarlander", {"size": 3}, "does not support the options \\['size'\\]"),
    ],
)
def test_bad_requests_are_named(family: str, kwargs: dict, message: str) -> None:
    arguments = {"seed": 0, "num_agents": 2, "level": 0.5, **kwargs}
    with pytest.raises(ValueError, match=message):
        make_variants(family, **arguments)
