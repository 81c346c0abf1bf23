"""Every environment family as a gymnasium id: ``gym.make("fedhpg/<Name>-v<N>", level=…,
index=…, num_agents=…, seed=…)`` is the federation's agent ``index`` (its variant parameters,
and the observations and rewards of the batch env that agent samples from, for the same reset
seed and actions), and passes gymnasium's own env checker."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.families import GYM_FAMILIES
from fedhpg.envs.gym_ids import GYM_IDS

ENVIRONMENTS_PAGE = Path(__file__).parents[1] / "docs" / "environments.md"
SHIPPED = ["gridworld", *GYM_FAMILIES]
"""The families fedhpg ships (the registry's, less ``gym``, which runs any id)."""
LEVEL, NUM_AGENTS, SEED, INDEX = 0.8, 3, 7, 2
STEPS = 40


def _federation_variant(family: str):  # the agent's variant, as a run computes it
    run = compose(
        [
            f"env.family={family}",
            f"env.level={LEVEL}",
            f"seed={SEED}",
            f"agents.num_agents={NUM_AGENTS}",
            "agents=homogeneous4",
            f"agents.num_agents={NUM_AGENTS}",
        ]
    )
    return run_variants(run)[INDEX]


def _rollout(env: Any, actions: list[Any]) -> list[tuple[np.ndarray, float, bool]]:
    steps = [(np.asarray(env.reset(seed=123)[0], dtype=np.float64), 0.0, False)]
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        steps.append((np.asarray(obs, dtype=np.float64), float(reward), bool(terminated)))
        if terminated or truncated:
            break
    return steps


def _batch_rollout(batch: Any, actions: list[Any]) -> list[tuple[np.ndarray, float, bool]]:
    steps = [(np.asarray(batch.reset(seed=123)[0], dtype=np.float64), 0.0, False)]
    for action in actions:
        step = batch.step(np.asarray([action]))
        steps.append(
            (step.obs[0].astype(np.float64), float(step.reward[0]), bool(step.terminated[0]))
        )
        if step.terminated[0] or step.truncated[0]:
            break
    return steps


def _actions(space: gym.Space) -> list[Any]:
    rng = np.random.default_rng(0)
    if isinstance(space, gym.spaces.Box):
        return [rng.uniform(space.low, space.high).astype(space.dtype) for _ in range(STEPS)]
    assert isinstance(space, gym.spaces.Discrete)
    return [int(rng.integers(int(space.n))) for _ in range(STEPS)]


@pytest.mark.parametrize("family", sorted(GYM_IDS))
def test_the_gym_id_is_the_federation_agents_mdp(family: str) -> None:
    env = gym.make(GYM_IDS[family], level=LEVEL, index=INDEX, num_agents=NUM_AGENTS, seed=SEED)
    variant = _federation_variant(family)
    single, batch = variant.make_env(), variant.make_batch_env(1)
    try:
        assert env.unwrapped.spec is not None and env.unwrapped.spec.id == GYM_IDS[family]
        assert env.observation_space == batch.single_observation_space
        assert env.action_space == batch.single_action_space
        actions = _actions(env.action_space)
        mine = _rollout(env, actions)
        assert len(mine) > 1
        for got, want in zip(mine, _rollout(single, actions), strict=True):
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1:] == want[1:]
        if family == "gridworld":
            # Its batch env draws slips from another stream: compare the MDP's tables instead.
            np.testing.assert_array_equal(
                env.unwrapped.transition_probs(),  # type: ignore[attr-defined]
                single.unwrapped.transition_probs(),  # type: ignore[attr-defined]
            )
            assert variant.params["slip"] == env.unwrapped.slip  # type: ignore[attr-defined]
            return
        for got, want in zip(mine, _batch_rollout(batch, actions), strict=True):
            np.testing.assert_allclose(got[0], want[0], rtol=1e-6)
            # float32 actions: the batch env sums the action cost in float32
            assert got[1] == pytest.approx(want[1], rel=1e-6, abs=1e-9)
            assert got[2] == want[2]
    finally:
        for closing in (env, single, batch):
            closing.close()


def test_variant_parameters_differ_by_index_and_follow_the_seed() -> None:
    def length(**kwargs: object) -> float:
        env = gym.make("fedhpg/CartPole-v1", level=1.0, num_agents=4, **kwargs)
        try:
            return float(env.unwrapped.length)  # type: ignore[attr-defined]
        finally:
            env.close()

    lengths = [length(index=k, seed=0) for k in range(4)]
    assert len(set(lengths)) == 4, "each index is another agent's variant"
    assert length(index=1, seed=0) == lengths[1] and length(index=1, seed=1) != lengths[1]
    with pytest.raises(ValueError, match="index must be in"):
        gym.make("fedhpg/CartPole-v1", index=4, num_agents=4)


@pytest.mark.parametrize("env_id", sorted(GYM_IDS.values()))
def test_gymnasiums_env_checker_passes(env_id: str) -> None:
    env = gym.make(env_id, level=0.5, index=1, seed=3)
    try:
        check_env(env, skip_render_check=True)  # rendering needs a display
    finally:
        env.close()


def test_the_ids_resolve_in_a_process_that_never_imported_fedhpg() -> None:
    code = (
        "import sys, gymnasium as gym\n"
        "env = gym.make('fedhpg.envs:fedhpg/Acrobot-v1', level=0.5, index=1, seed=0)\n"
        "assert 'fedhpg' in ''.join(sys.modules)\n"
        "print(env.unwrapped.LINK_LENGTH_1)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    expected = gym.make("fedhpg/Acrobot-v1", level=0.5, index=1, seed=0).unwrapped
    assert float(done.stdout.split()[-1]) == pytest.approx(expected.LINK_LENGTH_1, rel=1e-12)


def test_every_shipped_family_has_an_id_and_the_environments_page_names_it() -> None:
    page = ENVIRONMENTS_PAGE.read_text(encoding="utf-8")
    section = page.split("## Each agent's MDP as a gymnasium id", 1)[1].split("\n## ", 1)[0]
    assert not [family for family in SHIPPED if family not in GYM_IDS], "a family without an id"
    unnamed = [GYM_IDS[family] for family in SHIPPED if f"`{GYM_IDS[family]}`" not in section]
    assert not unnamed, f"docs/environments.md does not name {unnamed}"
