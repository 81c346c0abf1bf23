"""The paper's GridWorld: gymnasium conformance, exact dynamics, batched env, the generator."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fedhpg.envs.gridworld import (
    DEFAULT_LAYOUT,
    GridWorldBatchEnv,
    GridWorldEnv,
    make_gridworld_variants,
    parse_layout,
    shortest_path_policy,
)

LAYOUT = ("S..", "X..", "..G")


def test_registered_env_passes_check_env() -> None:
    env = gym.make("fedhpg/GridWorld-v0")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_generated_variants_pass_check_env() -> None:
    for variant in make_gridworld_variants(seed=0, num_agents=4, level=0.6):
        check_env(variant.make_env(), skip_render_check=True)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"slip": 1.5}, "slip must be in \\[0, 1\\), got 1.5"),
        ({"max_steps": 0}, "max_steps must be a positive integer, got 0"),
        ({"layout": ("S.Q", "..G")}, "unknown cell characters \\['Q'\\]"),
        ({"layout": ("...", "..G")}, "exactly one start 'S', got 0"),
        ({"layout": ("S..", "...")}, "at least one goal"),
        ({"layout": ("S..", "..")}, "equal length"),
        ({"render_mode": "human"}, "render_mode must be None or 'ansi'"),
    ],
)
def test_bad_arguments_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        GridWorldEnv(**kwargs)


def test_rewards_termination_and_success() -> None:
    env = GridWorldEnv(layout=LAYOUT, slip=0.0, max_steps=10)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(1)  # down, onto the obstacle
    assert (reward, terminated, info["is_success"]) == (-1.0, True, False)
    env.reset(seed=0)
    for action in (3, 3, 1):  # right, right, down: (0,0) → (0,1) → (0,2) → (1,2)
        obs, reward, terminated, _, _ = env.step(action)
        assert (reward, terminated) == (0.0, False)
    obs, reward, terminated, truncated, info = env.step(1)  # down onto the goal
    assert (int(obs), reward, terminated, truncated, info["is_success"]) == (
        8,
        1.0,
        True,
        False,
        True,
    )


def test_walls_keep_the_agent_in_place_and_truncation() -> None:
    env = GridWorldEnv(layout=LAYOUT, slip=0.0, max_steps=3)
    env.reset(seed=0)
    for step in range(3):
        obs, _, terminated, truncated, _ = env.step(0)  # up: into the wall
        assert int(obs) == 0 and not terminated
        assert truncated == (step == 2)


def test_render_ansi_marks_the_agent() -> None:
    env = GridWorldEnv(layout=LAYOUT, render_mode="ansi")
    env.reset(seed=0)
    assert env.render() == "A..\nX..\n..G"


def test_transition_table_is_a_distribution() -> None:
    probs = GridWorldEnv(layout=DEFAULT_LAYOUT, slip=0.2).transition_probs()
    np.testing.assert_allclose(probs.sum(axis=-1), 1.0)
    model = parse_layout(DEFAULT_LAYOUT)
    assert probs[0, 3, 1] == pytest.approx(0.8)  # right from the start, no slip
    assert probs[0, 3, 0] == pytest.approx(0.2 / 3 * 2)  # slips up or left: blocked by walls
    terminal = np.flatnonzero(model.terminal)[0]
    assert probs[terminal, :, terminal].tolist() == [1.0] * 4


@pytest.mark.parametrize(("state", "action"), [(0, 3), (7, 1), (12, 2)])
def test_batched_env_follows_the_exact_dynamics(state: int, action: int) -> None:
    """From one state, the next-state frequencies of 200k batched copies sit within 4 standard
    errors of P[s, a, :] (binomial proportion per next state)."""
    slip = 0.3
    probs = GridWorldEnv(layout=DEFAULT_LAYOUT, slip=slip).transition_probs()[state, action]
    n = 200_000
    env = GridWorldBatchEnv(layout=DEFAULT_LAYOUT, slip=slip, max_steps=50, num_envs=n)
    env.reset(seed=1)
    env._state[:] = state
    step = env.step(np.full(n, action))
    freq = np.bincount(step.obs, minlength=probs.size) / n
    stderr = np.sqrt(probs * (1 - probs) / n)
    assert np.all(np.abs(freq - probs) <= 4 * stderr + 1e-12)


def test_single_env_follows_the_exact_dynamics() -> None:
    slip, state, action, n = 0.3, 0, 3, 20_000
    probs = GridWorldEnv(layout=DEFAULT_LAYOUT, slip=slip).transition_probs()[state, action]
    env = GridWorldEnv(layout=DEFAULT_LAYOUT, slip=slip)
    env.reset(seed=0)
    counts = np.zeros(probs.size)
    for _ in range(n):
        env._state = state
        obs, *_ = env.step(action)
        counts[int(obs)] += 1
    stderr = np.sqrt(probs * (1 - probs) / n)
    assert np.all(np.abs(counts / n - probs) <= 4 * stderr + 1e-12)


def test_batched_env_rewards_termination_truncation() -> None:
    env = GridWorldBatchEnv(layout=LAYOUT, slip=0.0, max_steps=2, num_envs=3)
    env.reset(seed=0)
    step = env.step(np.array([1, 3, 0]))  # obstacle, right, wall
    np.testing.assert_array_equal(step.reward, [-1.0, 0.0, 0.0])
    np.testing.assert_array_equal(step.terminated, [True, False, False])
    np.testing.assert_array_equal(step.truncated, [False, False, False])
    step = env.step(np.array([0, 0, 0]))
    np.testing.assert_array_equal(step.truncated[1:], [True, True])
    assert not step.success.any()


def test_batched_env_is_deterministic_under_seed() -> None:
    def run(seed: int) -> np.ndarray:
        env = GridWorldBatchEnv(layout=DEFAULT_LAYOUT, slip=0.3, max_steps=50, num_envs=64)
        env.reset(seed=seed)
        actions = np.random.default_rng(0).integers(0, 4, size=(20, 64))
        return np.stack([env.step(a).obs for a in actions])

    np.testing.assert_array_equal(run(5), run(5))
    assert not np.array_equal(run(5), run(6))


def test_generator_is_deterministic_and_heterogeneous() -> None:
    first = make_gridworld_variants(seed=0, num_agents=4, level=0.6)
    assert first == make_gridworld_variants(seed=0, num_agents=4, level=0.6)
    assert first != make_gridworld_variants(seed=1, num_agents=4, level=0.6)
    keys = {(v.layout, v.slip, v.gamma) for v in first}
    assert len(keys) == 4, "four distinct variants"
    assert len({v.layout for v in first}) > 1 and len({v.slip for v in first}) > 1
    assert len({str(v.signature()) for v in first}) == 1, "identical spaces"
    identical = make_gridworld_variants(seed=0, num_agents=4, level=0.0)
    assert len({(v.layout, v.slip, v.gamma) for v in identical}) == 1


def test_generator_rejects_bad_level() -> None:
    with pytest.raises(ValueError, match=r"level must be in \[0, 1\], got 1.5"):
        make_gridworld_variants(seed=0, num_agents=2, level=1.5)


def test_vary_goal_gives_conflicting_goals() -> None:
    variants = make_gridworld_variants(seed=0, num_agents=6, level=0.5, vary_goal=True)
    assert len({tuple(v.params["goal"]) for v in variants}) > 1


def _success_probability(variant, policy: np.ndarray) -> float:
    """P(reach a goal within max_steps) under a deterministic policy, by exact propagation."""
    env = variant.make_env()
    probs = env.transition_probs()
    model = env.model
    dist = np.zeros(model.num_cells)
    dist[model.start] = 1.0
    reached = 0.0
    for _ in range(variant.max_steps):
        moving = dist * ~model.terminal
        dist = np.einsum("s,st->t", moving, probs[np.arange(model.num_cells), policy])
        reached += dist[model.goal].sum()
        dist[model.terminal] = 0.0
    return reached


def test_one_common_policy_solves_the_demo_variants() -> None:
    """The demo's variants admit one policy with success ≥ 0.9 in every environment."""
    variants = make_gridworld_variants(seed=0, num_agents=4, level=0.6)
    policy = shortest_path_policy(variants[0].layout, [v.layout for v in variants[1:]])
    for variant in variants:
        assert _success_probability(variant, policy) >= 0.9, variant.params
