"""The paper's GridWorld: gymnasium conformance, exact dynamics, batched env, the generator."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fedhpg.envs.base import BatchEnv
from fedhpg.envs.gridworld import (
    DEFAULT_LAYOUT,
    ENV_ID,
    GridWorldBatchEnv,
    GridWorldEnv,
    GridWorldVariant,
    demo_variants,
    make_gridworld_variants,
    register_envs,
    shortest_path_policy,
    success_probability,
)

LAYOUT = ("S..", "X..", "..G")
Z_LIMIT = 4.0  # standard errors of a binomial proportion


def _with_start(layout: Sequence[str], state: int) -> tuple[str, ...]:
    """``layout`` with its start moved to cell ``state`` (an empty cell)."""
    cells = list("".join(layout).replace("S", "."))
    assert cells[state] == "."
    cells[state] = "S"
    width = len(layout[0])
    return tuple("".join(cells[r : r + width]) for r in range(0, len(cells), width))


def _assert_close_to(counts: np.ndarray, probs: np.ndarray) -> None:
    n = counts.sum()
    stderr = np.sqrt(probs * (1 - probs) / n)
    assert np.all(np.abs(counts / n - probs) <= Z_LIMIT * stderr + 1e-12), (counts / n, probs)


def _common_policy(variants: Sequence[GridWorldVariant]) -> np.ndarray:
    first = variants[0]
    return shortest_path_policy(
        first.layout, [v.layout for v in variants[1:]], path=first.safe_path
    )


def _check_env_strictly(env: gym.Env) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env)
    env.close()


def test_registered_env_passes_check_env() -> None:
    register_envs()  # idempotent: the package import already registered it
    _check_env_strictly(gym.make(ENV_ID).unwrapped)
    assert gym.spec(ENV_ID).kwargs["max_steps"] == 50


@pytest.mark.parametrize("vary_goal", [False, True])
def test_generated_variants_pass_check_env(vary_goal: bool) -> None:
    for variant in make_gridworld_variants(seed=0, num_agents=4, level=0.6, vary_goal=vary_goal):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env(variant.make_env(render_mode="ansi"), skip_render_check=True)
        assert isinstance(variant.make_batch_env(2), BatchEnv)
        assert variant.max_episode_steps == 50


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"slip": 1.5}, r"slip must be in \[0, 1\), got 1.5"),
        ({"slip": -0.1}, r"slip must be in \[0, 1\), got -0.1"),
        ({"max_steps": 0}, "max_steps must be a positive integer, got 0"),
        ({"layout": ("S.Q", "..G")}, r"unknown cell characters \['Q'\]"),
        ({"layout": ("...", "..G")}, "exactly one start 'S', got 0"),
        ({"layout": ("S.S", "..G")}, "exactly one start 'S', got 2"),
        ({"layout": ("S..", "...")}, "at least one goal"),
        ({"layout": ("S..", "..")}, r"equal length, got \[3, 2\]"),
        ({"layout": "S.G"}, "sequence of row strings, got the string 'S.G'"),
        ({"render_mode": "human"}, "render_mode must be None or 'ansi', got 'human'"),
    ],
)
def test_bad_arguments_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        GridWorldEnv(**kwargs)


def test_bad_batch_and_variant_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="num_envs must be a positive integer, got 0"):
        GridWorldBatchEnv(layout=LAYOUT, slip=0.0, max_steps=5, num_envs=0)
    with pytest.raises(ValueError, match=r"slip must be in \[0, 1\), got 1.0"):
        GridWorldBatchEnv(layout=LAYOUT, slip=1.0, max_steps=5, num_envs=2)
    with pytest.raises(ValueError, match=r"gamma must be in \(0, 1\], got 1.5"):
        GridWorldVariant(index=0, gamma=1.5, layout=LAYOUT)
    with pytest.raises(ValueError, match="unknown cell characters"):
        GridWorldVariant(index=0, gamma=0.9, layout=("S?G",))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"level": 1.5}, r"level must be in \[0, 1\], got 1.5"),
        ({"level": -0.2}, r"level must be in \[0, 1\], got -0.2"),
        ({"level": math.nan}, r"level must be in \[0, 1\], got nan"),
        ({"level": 0.5, "num_agents": 0}, "num_agents must be >= 1, got 0"),
        ({"level": 0.5, "size": 2}, "size must be >= 3, got 2"),
        ({"level": 0.5, "max_steps": -3}, "max_steps must be a positive integer, got -3"),
    ],
)
def test_generator_rejects_bad_arguments(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        make_gridworld_variants(**{"seed": 0, "num_agents": 2, **kwargs})


def test_rewards_termination_and_success() -> None:
    env = GridWorldEnv(layout=LAYOUT, slip=0.0, max_steps=10)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(1)  # down, onto the obstacle
    assert (reward, terminated, info["is_success"]) == (-1.0, True, False)
    env.reset(seed=0)
    for action in (3, 3, 1):  # right, right, down: (0,0) → (0,1) → (0,2) → (1,2)
        obs, reward, terminated, _, info = env.step(action)
        assert (reward, terminated, info["is_success"]) == (0.0, False, False)
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
    for step, action in enumerate((0, 2, 0)):  # up, left, up: into the walls
        obs, _, terminated, truncated, _ = env.step(action)
        assert int(obs) == 0 and not terminated
        assert truncated == (step == 2)


def test_single_env_rejects_bad_actions() -> None:
    env = GridWorldEnv(layout=LAYOUT)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must be 0\.\.3, got 4"):
        env.step(4)


def test_render_ansi_marks_the_agent() -> None:
    env = GridWorldEnv(layout=LAYOUT, render_mode="ansi")
    env.reset(seed=0)
    assert env.render() == "A..\nX..\n..G"
    env.step(3)
    assert env.render() == "SA.\nX..\n..G"
    assert GridWorldEnv(layout=LAYOUT).render() is None


def test_model_tables() -> None:
    env = GridWorldEnv(layout=DEFAULT_LAYOUT, slip=0.2)
    probs = env.transition_probs()
    assert probs.shape == (25, 4, 25) and probs.dtype == np.float64
    np.testing.assert_allclose(probs.sum(axis=-1), 1.0)
    assert probs[0, 3, 1] == pytest.approx(0.8)  # right from the start, no slip
    assert probs[0, 3, 5] == pytest.approx(0.2 / 3)  # slips down
    assert probs[0, 3, 0] == pytest.approx(0.2 / 3 * 2)  # slips up or left: walls
    terminal = env.terminal_mask()
    assert terminal.dtype == bool
    np.testing.assert_array_equal(np.flatnonzero(terminal), [6, 8, 16, 18, 24])
    reward = env.reward_table()
    assert reward[24] == 1.0 and reward[6] == -1.0 and reward[~terminal].tolist() == [0.0] * 20
    for cell in np.flatnonzero(terminal):
        assert probs[cell, :, cell].tolist() == [1.0] * 4


@pytest.mark.parametrize(("state", "action"), [(0, 3), (7, 1), (12, 2), (4, 0), (23, 3)])
def test_batched_env_follows_the_exact_dynamics(state: int, action: int) -> None:
    """From one state, the next-state frequencies of 200k batched copies sit within 4 standard
    errors of P[s, a, :] (binomial proportion per next state)."""
    layout, slip, n = _with_start(DEFAULT_LAYOUT, state), 0.3, 200_000
    probs = GridWorldEnv(layout=layout, slip=slip).transition_probs()[state, action]
    env = GridWorldBatchEnv(layout=layout, slip=slip, max_steps=50, num_envs=n)
    assert env.reset(seed=1).tolist() == [state] * n
    step = env.step(np.full(n, action))
    _assert_close_to(np.bincount(step.obs, minlength=probs.size), probs)
    np.testing.assert_array_equal(step.reward, env.model.reward[step.obs])
    np.testing.assert_array_equal(step.terminated, env.model.terminal[step.obs])
    np.testing.assert_array_equal(step.success, step.obs == 24)


def test_single_env_follows_the_exact_dynamics() -> None:
    state, action, slip, n = 7, 1, 0.3, 20_000
    layout = _with_start(DEFAULT_LAYOUT, state)
    env = GridWorldEnv(layout=layout, slip=slip)
    probs = env.transition_probs()[state, action]
    env.reset(seed=0)
    counts = np.zeros(probs.size)
    for _ in range(n):
        env.reset()
        obs, *_ = env.step(action)
        counts[int(obs)] += 1
    _assert_close_to(counts, probs)


def test_batched_env_agrees_with_the_gym_env_without_slip() -> None:
    """Without slip both are deterministic: same actions, same outputs, step by step."""
    num_envs, max_steps = 16, 12
    batch = GridWorldBatchEnv(
        layout=DEFAULT_LAYOUT, slip=0.0, max_steps=max_steps, num_envs=num_envs
    )
    batch.reset(seed=0)
    singles = [GridWorldEnv(layout=DEFAULT_LAYOUT, max_steps=max_steps) for _ in range(num_envs)]
    for env in singles:
        env.reset(seed=0)
    alive = np.ones(num_envs, dtype=bool)
    actions = np.random.default_rng(3).integers(0, 4, size=(max_steps, num_envs))
    for row in actions:
        step = batch.step(row)
        for k in np.flatnonzero(alive):
            obs, reward, terminated, truncated, info = singles[k].step(int(row[k]))
            got = (step.obs[k], step.reward[k], step.terminated[k], step.truncated[k])
            assert got == (obs, reward, terminated, truncated)
            assert step.success[k] == info["is_success"]
        alive &= ~(step.terminated | step.truncated)
    assert not alive.any(), "every copy ended by max_steps"


def test_batched_env_rewards_termination_truncation() -> None:
    env = GridWorldBatchEnv(layout=LAYOUT, slip=0.0, max_steps=2, num_envs=4)
    env.reset(seed=0)
    step = env.step(np.array([1, 3, 0, 3]))  # obstacle, right, wall, right
    assert step.obs.dtype == np.int64 and step.reward.dtype == np.float64
    np.testing.assert_array_equal(step.obs, [3, 1, 0, 1])
    np.testing.assert_array_equal(step.reward, [-1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(step.terminated, [True, False, False, False])
    np.testing.assert_array_equal(step.truncated, [False, False, False, False])
    assert not step.success.any()
    step = env.step(np.array([0, 0, 0, 3]))
    np.testing.assert_array_equal(step.truncated[1:], [True, True, True])
    env.reset(seed=0)
    for action in (3, 3, 1, 1):
        step = env.step(np.full(4, action))
        if step.terminated.any():
            break
    assert step.success.all() and step.terminated.all() and (step.reward == 1.0).all()
    assert not step.truncated.any(), "reaching the goal on the last step is not a truncation"


def test_batched_env_rejects_bad_actions() -> None:
    env = GridWorldBatchEnv(layout=LAYOUT, slip=0.2, max_steps=5, num_envs=3)
    env.reset(seed=0)
    expected = r"3 integers in 0\.\.3, got shape \(3,\), dtype int64 and values \[0, 4\]"
    with pytest.raises(ValueError, match=expected):
        env.step(np.array([0, 4, 0]))
    with pytest.raises(ValueError, match=r"values \[-1, 0\]"):
        env.step(np.array([0, -1, 0]))
    with pytest.raises(ValueError, match="dtype float64"):
        env.step(np.array([0.0, 1.0, 2.0]))
    with pytest.raises(ValueError, match=r"got shape \(2,\)"):
        env.step(np.array([0, 1]))
    assert env.step(np.array([3, 3, 3], dtype=np.uint8)).obs.shape == (3,)


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
    assert len({(v.layout, v.slip, v.gamma) for v in first}) == 4, "four distinct variants"
    assert len({v.layout for v in first}) > 1 and len({v.slip for v in first}) > 1
    assert len({v.gamma for v in first}) > 1
    assert [v.index for v in first] == [0, 1, 2, 3]
    assert all(v.family == "gridworld" and v.params["slip"] == v.slip for v in first)
    assert len({str(v.signature()) for v in first}) == 1, "identical spaces"


@pytest.mark.parametrize("seed", range(5))
def test_level_zero_is_identical_and_positive_levels_differ(seed: int) -> None:
    identical = make_gridworld_variants(seed=seed, num_agents=4, level=0.0)
    assert len({(v.layout, v.slip, v.gamma) for v in identical}) == 1
    assert identical[0].slip == 0.0 and identical[0].params["obstacles"] == 0
    for level in (0.1, 0.5, 1.0):
        variants = make_gridworld_variants(seed=seed, num_agents=8, level=level)
        assert len({(v.layout, v.slip, v.gamma) for v in variants}) == 8, level
        assert all(0.0 <= v.slip <= 0.1 * level for v in variants)
        assert all(0.99 - 0.09 * level <= v.gamma <= 0.99 for v in variants)
    most = make_gridworld_variants(seed=seed, num_agents=8, level=1.0)
    assert len({v.layout for v in most}) > 1, "level 1 does not block every layout alike"


def test_obstacles_grow_with_level() -> None:
    levels = np.linspace(0.0, 1.0, 11)
    counts = [
        [v.params["obstacles"] for v in make_gridworld_variants(seed=s, num_agents=2, level=lv)]
        for s in range(10)
        for lv in levels
    ]
    per_level = np.array(counts).reshape(10, len(levels), 2)
    assert np.all(np.diff(per_level, axis=1) >= 0)
    assert per_level[:, -1].min() > 0


@pytest.mark.parametrize("seed", range(20))
def test_obstacles_stay_off_and_away_from_the_safe_path(seed: int) -> None:
    for variant in make_gridworld_variants(seed=seed, num_agents=4, level=1.0):
        cells = "".join(variant.layout)
        path = variant.safe_path
        assert path[0] == 0 and cells[path[-1]] == "G" and len(path) == 9
        rows, cols = np.divmod(np.array(path), 5)
        assert np.all(np.abs(np.diff(rows)) + np.abs(np.diff(cols)) == 1), "4-connected"
        for cell in np.flatnonzero(np.array(list(cells)) == "X"):
            r, c = divmod(int(cell), 5)
            assert np.min(np.abs(rows - r) + np.abs(cols - c)) >= 2, (variant.layout, path)


def test_vary_goal_gives_distinct_conflicting_goals() -> None:
    variants = make_gridworld_variants(seed=0, num_agents=6, level=0.5, vary_goal=True)
    goals = [tuple(v.params["goal"]) for v in variants]
    assert len(set(goals)) == 6
    for variant, (r, c) in zip(variants, goals, strict=True):
        assert variant.layout[r][c] == "G" and "".join(variant.layout).count("G") == 1
        assert success_probability(variant.make_env()) >= 0.9, "each task is solvable alone"
    assert len({str(v.signature()) for v in variants}) == 1


@pytest.mark.parametrize("level", [0.5, 0.6])
def test_one_common_policy_solves_the_demo_variants(level: float) -> None:
    """The demo set: the path-following common policy reaches the goal with probability ≥ 0.9
    within max_steps in every environment (exact dynamic programming)."""
    variants = make_gridworld_variants(seed=0, num_agents=4, level=level)
    policy = _common_policy(variants)
    for variant in variants:
        env = variant.make_env()
        common = success_probability(env, policy)
        assert common >= 0.9, (variant.params, common)
        assert common <= success_probability(env) + 1e-12, "the best env-specific policy"


def test_demo_variants_are_the_default_run() -> None:
    assert demo_variants() == make_gridworld_variants(seed=0, num_agents=4, level=0.6)


def test_common_policy_solves_every_variant_up_to_level_0_6() -> None:
    for seed in range(20):
        for level in (0.2, 0.4, 0.6):
            variants = make_gridworld_variants(seed=seed, num_agents=4, level=level)
            policy = _common_policy(variants)
            for variant in variants:
                common = success_probability(variant.make_env(), policy)
                assert common >= 0.9, (seed, level, variant.layout, variant.slip, common)


def test_success_probability_matches_batched_sampling() -> None:
    """The dynamic programme and the batched sampler agree on one policy's success rate."""
    variant = make_gridworld_variants(seed=1, num_agents=1, level=1.0)[0]
    policy = np.random.default_rng(0).integers(0, 4, size=25)
    policy[list(variant.safe_path[:-1])] = _common_policy([variant])[list(variant.safe_path[:-1])]
    exact = success_probability(variant.make_env(), policy)
    n = 50_000
    env = variant.make_batch_env(n)
    obs = env.reset(seed=0)
    done, success = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    for _ in range(variant.max_episode_steps):
        step = env.step(policy[obs])
        success |= step.success & ~done
        done |= step.terminated | step.truncated
        obs = step.obs
    assert done.all()
    _assert_close_to(np.array([n - success.sum(), success.sum()]), np.array([1 - exact, exact]))
