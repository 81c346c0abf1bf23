"""``env=gym env.id=ID``: any registered gymnasium id as a heterogeneous family, what differs
between agents declared in ``env.vary``. Tested on three ids the project ships no family for
(MountainCar-v0's attributes, FrozenLake-v1's constructor keywords, Acrobot-v1 through
gymnasium's own class): the values reach the environments the agents sample from, agent k's
draw depends on (seed, k, name) alone, the variants pass gymnasium's checker, mistakes are one
line, and (``make test-long``) each id learns above a random policy."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from procs import BIN

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.heterogeneity.variants import run_variants, variant_of
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.gym_variant import GymVariant

MOUNTAIN_CAR = [
    "env=gym",
    "env.id=MountainCar-v0",
    "+env.vary.force={spread: 0.5}",
    "+env.vary.gravity={uniform: {low: 0.002, high: 0.003}}",
]
FROZEN_LAKE = [
    "env=gym",
    "env.id=FrozenLake-v1",
    "+env.vary.success_rate={uniform: {low: 0.34, high: 0.9}}",
    "+env.vary.gamma={choice: [0.95, 0.99]}",
    "+env.kwargs.map_name=8x8",
]
ACROBOT = ["env=gym", "env.id=Acrobot-v1", "+env.vary.LINK_MASS_1={spread: 0.4}"]


def _variant(overrides: list[str], index: int = 0) -> GymVariant:
    variant = variant_of(compose(overrides), index)
    assert isinstance(variant, GymVariant)
    return variant


def test_attributes_reach_every_copy_the_agent_samples_from() -> None:
    variants = list(run_variants(compose(MOUNTAIN_CAR)))
    forces = [v.attributes["force"] for v in variants]
    assert len(set(forces)) == 4 and all(0.0005 <= f <= 0.0015 for f in forces), forces
    assert all(0.002 <= v.attributes["gravity"] <= 0.003 for v in variants)
    batch = variants[2].make_batch_env(3)
    try:
        copies = batch._envs  # type: ignore[attr-defined]
        assert {env.force for env in copies} == {variants[2].attributes["force"]}
    finally:
        batch.close()
    env = variants[2].make_env()
    assert env.unwrapped.gravity == variants[2].attributes["gravity"]  # type: ignore[attr-defined]
    env.close()


def test_constructor_keywords_and_the_discount_vary_per_agent() -> None:
    variants = list(run_variants(compose(FROZEN_LAKE)))
    rates = [v.env_kwargs["success_rate"] for v in variants]
    assert len(set(rates)) == 4 and all(0.34 <= r <= 0.9 for r in rates)
    assert {v.gamma for v in variants} <= {0.95, 0.99}
    assert all(v.env_kwargs["map_name"] == "8x8" for v in variants), "env.kwargs: every agent"
    env = variants[1].make_env()
    transitions = env.unwrapped.P[9][1]  # type: ignore[attr-defined]  # a state's "down"
    assert max(p for p, *_ in transitions) == pytest.approx(rates[1]), "the intended move"
    assert env.observation_space.n == 64  # type: ignore[attr-defined]
    env.close()


def test_level_zero_is_the_stock_environment_and_draws_ignore_k() -> None:
    stock = _variant([*MOUNTAIN_CAR[:3], "env.level=0"])
    assert stock.attributes["force"] == 0.001, "a spread at level 0 is the env's own value"
    small = list(run_variants(compose([*MOUNTAIN_CAR, "agents.num_agents=4"])))
    large = list(run_variants(compose([*MOUNTAIN_CAR, "agents=homogeneous10"])))
    assert [v.attributes for v in small] == [v.attributes for v in large[:4]]
    other_seed = list(run_variants(compose([*MOUNTAIN_CAR, "seed=1"])))
    assert [v.attributes for v in small] != [v.attributes for v in other_seed]


@pytest.mark.parametrize("overrides", [MOUNTAIN_CAR, FROZEN_LAKE, ACROBOT])
def test_every_variant_passes_gymnasiums_checker(overrides: list[str]) -> None:
    env = _variant(overrides, index=3).make_env()
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_a_horizon_beyond_the_registered_limit_is_the_episode_limit() -> None:
    variant = _variant([*MOUNTAIN_CAR, "env.horizon=300"])
    assert variant.max_episode_steps == 300 and gym.spec("MountainCar-v0").max_episode_steps == 200
    batch = variant.make_batch_env(1)
    try:
        batch.reset(seed=0)
        steps = 0
        while True:
            step = batch.step(np.ones(1, dtype=np.int64))  # idle: never reaches the goal
            steps += 1
            if step.truncated[0] or step.terminated[0]:
                break
        assert steps == 300 and step.truncated[0]
    finally:
        batch.close()


@pytest.mark.parametrize(
    ("overrides", "key", "says"),
    [
        (["env=gym"], "env.id", "env=gym needs a registered gymnasium id"),
        (["env=gym", "env.id=NoSuchEnv-v0"], "env.id", "'NoSuchEnv-v0'"),
        (
            ["env=gym", "env.id=MountainCar-v0", "+env.vary.wheels={spread: 0.1}"],
            "env.vary.wheels",
            "has no constructor keyword or attribute 'wheels'",
        ),
        (
            ["env=gym", "env.id=MountainCar-v0", "+env.vary.force={spread: -1}"],
            "env.vary.force",
            "a spread is {spread: s}, s >= 0",
        ),
        (
            ["env=gym", "env.id=MountainCar-v0", "+env.vary.force={normal: 1}"],
            "env.vary.force",
            "needs exactly one of choice, uniform, lognormal",
        ),
        (["env=cartpole", "env.id=MountainCar-v0"], "env.id", "read by env=gym"),
    ],
)
def test_mistakes_name_the_key(overrides: list[str], key: str, says: str) -> None:
    with pytest.raises(ConfigError) as caught:
        compose(overrides)
    assert caught.value.key == key and says in str(caught.value), str(caught.value)


def test_fedhpg_run_runs_a_gymnasium_id_with_agent_processes(tmp_path: Path) -> None:
    result = subprocess.run(
        [
            str(BIN / "fedhpg-run"),
            *ACROBOT,
            "agents=homogeneous4",
            "agents.budget.batch_size=[2]",
            "rounds=2",
            "eval.episodes=1",
            "env.horizon=50",
            f"server.out_dir={tmp_path / 'run'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=180,
        env={**os.environ, "FEDHPG_LOG_LEVEL": "WARNING"},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [line for line in result.stdout.splitlines() if line.startswith("agent-")]
    assert len(rows) == 4 and all("LINK_MASS_1=" in row for row in rows), result.stdout


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["MountainCar-v0", "Acrobot-v1", "FrozenLake-v1"])
def test_each_id_learns_above_a_random_policy(env_id: str) -> None:
    """benchmarks/gym_ids.py's budgets (BENCHMARKS.md), seed 0."""
    from benchmarks.gym_ids import CASES, measure

    outcome = measure(CASES[env_id], seed=0)
    assert outcome["learned_return"] > outcome["random_return"], outcome
