"""Variants made per agent index: the same variants as the K-list, without the K-list.

At K = 10 000 an agent host builds its own agents' variants and the server only what it needs;
these tests check that agent k's variant is bit-identical however it is asked for (pinned to
what the K-list made before variants were lazy), that the server's and the in-process start-up
hold no K-long list of variants and build no environment per agent (counted, not timed), and
that a plugin family offering only the K-list still works.
"""

from __future__ import annotations

import dataclasses
import hashlib
import weakref
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.variants import (
    ITERATION_CHUNK,
    run_variants,
    variant_of,
    variants_of,
)
from fedhpg.common.runtime.cli import compose
from fedhpg.envs import registry
from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.families import GYM_FAMILIES, _rows
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.mujoco_assets import without_settotalmass
from fedhpg.envs.registry import (
    FAMILIES,
    LazyFamily,
    make_variant,
    make_variants,
    make_variants_at,
    per_index_family,
)
from fedhpg.server.pools import FederationError

BUILT_IN = sorted({"gridworld", *GYM_FAMILIES})

GOLDEN = [
    # (family, seed, K, level, options, sha256 of the K variants' reprs): made by the K-list
    # code before variants were drawn per index (commit dbf5b2a), the HalfCheetah model path
    # (a temp file) replaced by <xml>.
    ("acrobot", 0, 1, 0.0, {}, "ce9ffcd0ab2cbedf"),
    ("acrobot", 3, 6, 0.7, {}, "1944a6acd1e20bc0"),
    ("acrobot", 11, 40, 1.0, {"gamma": 0.999}, "7f1113c319066995"),
    ("cartpole", 0, 1, 0.0, {}, "9fde4b0714f9ccbd"),
    ("cartpole", 3, 6, 0.7, {}, "5e7740043041efd8"),
    ("cartpole", 11, 40, 1.0, {"gamma": 0.999}, "b40a940ac8bb95f7"),
    ("gridworld", 0, 1, 0.0, {}, "6f27391a67b481b1"),
    ("gridworld", 3, 6, 0.7, {"size": 4}, "0a06944bae39451b"),
    ("gridworld", 11, 40, 1.0, {"vary_goal": True, "size": 6}, "bc96d66c187e1892"),
    ("halfcheetah", 0, 1, 0.0, {}, "3aefd2a77a74fe74"),
    ("halfcheetah", 3, 6, 0.7, {}, "8f408984e0ac73ad"),
    ("halfcheetah", 11, 40, 1.0, {"gamma": 0.999}, "d21198ded52931b1"),
    ("lunarlander", 0, 1, 0.0, {}, "62b01064f83085ab"),
    ("lunarlander", 3, 6, 0.7, {}, "dc54cc02d0f80dfa"),
    ("lunarlander", 11, 40, 1.0, {"gamma": 0.999}, "846995b6685da3e5"),
    ("lunarlander-continuous", 0, 1, 0.0, {}, "80b16ab20fe66251"),
    ("lunarlander-continuous", 3, 6, 0.7, {}, "1650216a71787c42"),
    ("lunarlander-continuous", 11, 40, 1.0, {"gamma": 0.999}, "ea1b0928d7370f38"),
    ("mountaincar", 0, 1, 0.0, {}, "196ea00d1eea140d"),
    ("mountaincar", 3, 6, 0.7, {}, "35b1d5e350752ba7"),
    ("mountaincar", 11, 40, 1.0, {"gamma": 0.999}, "ab8d64f5f545aeef"),
    ("pendulum", 0, 1, 0.0, {}, "be20624b8b1eebb0"),
    ("pendulum", 3, 6, 0.7, {}, "ee94e7451df2329d"),
    ("pendulum", 11, 40, 1.0, {"gamma": 0.999}, "6ff2e55d9d841b5d"),
]


def _exact(variants: Sequence[EnvVariant]) -> str:
    """Every field, floats written exactly (the dataclass repr), machine paths left out."""
    xml = without_settotalmass("half_cheetah.xml")[0]
    text = "\n".join(repr(v).replace(xml, "<xml>") for v in variants)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def test_every_built_in_family_is_pinned() -> None:
    assert {case[0] for case in GOLDEN} == set(BUILT_IN)


@pytest.mark.parametrize("case", GOLDEN, ids=lambda c: f"{c[0]}-K{c[2]}")
def test_each_index_alone_is_the_variant_the_k_list_made(case: tuple[Any, ...]) -> None:
    family, seed, num_agents, level, options, golden = case
    arguments = dict(seed=seed, num_agents=num_agents, level=level, **options)
    assert _exact(make_variants(family, **arguments)) == golden
    alone = [make_variant(family, k, **arguments) for k in range(num_agents)]
    assert _exact(alone) == golden
    # any subset, in any order, repeated: each the same variant
    picked = [num_agents - 1, 0, num_agents // 2, num_agents - 1]
    everything = make_variants(family, **arguments)
    assert [repr(v) for v in make_variants_at(family, picked, **arguments)] == [
        repr(everything[k]) for k in picked
    ]


@pytest.mark.parametrize("family", ["cartpole", "lunarlander"])  # rows of 6 and of 5
@pytest.mark.parametrize("seed", [0, 5])
def test_variant_k_does_not_depend_on_k(family: str, seed: int) -> None:
    """Agent k of a large run, built alone, is agent k of the (k+1)-agent run's list."""
    for index in (0, 1, 9_999):
        alone = make_variant(family, index, seed=seed, num_agents=10_000, level=0.8)
        listed = make_variants(family, seed=seed, num_agents=index + 1, level=0.8)[index]
        assert repr(alone) == repr(listed)


def test_rows_are_those_of_the_whole_matrix() -> None:
    """The documented draw: row k of default_rng([seed, tag]).uniform(−1, 1, (K, count)), here
    across spans (indices farther apart than SPAN_GAP are drawn after a jump)."""
    whole = np.random.default_rng([7, 0xCA27]).uniform(-1.0, 1.0, size=(20_000, 6))
    indices = [19_999, 3, 4, 3, 12_000, 0, 8_191, 8_192]
    assert np.array_equal(_rows(7, 0xCA27, indices, 6), whole[indices])
    assert _rows(7, 0xCA27, [], 6).shape == (0, 6)


def test_bad_indices_and_options_are_clear_errors() -> None:
    with pytest.raises(IndexError, match=r"agent index 4 is not in \[0, num_agents=4\)"):
        make_variant("cartpole", 4, seed=0, num_agents=4, level=0.5)
    with pytest.raises(IndexError):
        make_variant("gridworld", -1, seed=0, num_agents=4, level=0.5)
    with pytest.raises(ValueError, match=r"bad options for env family 'gridworld'.*bogus"):
        make_variant("gridworld", 0, seed=0, num_agents=4, level=0.5, bogus=1)
    with pytest.raises(ValueError, match="does not support the options"):
        make_variant("cartpole", 0, seed=0, num_agents=4, level=0.5, bogus=1)


def test_run_variants_is_a_lazy_sequence() -> None:
    run = compose(["env=cartpole", "agents=population", "agents.num_agents=3000"])
    variants = run_variants(run)
    assert len(variants) == 3000
    listed = make_variants(
        "cartpole", seed=run.seed, num_agents=3000, level=run.env.level, gamma=0.999
    )
    assert variants[-1] == listed[-1] == variant_of(run, 2999)
    assert variants[10:13] == listed[10:13]
    assert [repr(v) for v in variants] == [repr(v) for v in listed]
    assert list(variants_of(run, [5, 2, 5])) == [5, 2]
    with pytest.raises(IndexError):
        variants[3000]


# --- counting what a start-up builds ------------------------------------------------------------

BUILT: Counter[str] = Counter()
"""variants made, the most made by one call, the most alive at once, environments built."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class CountedVariant(GymVariant):
    """A CartPole variant that counts itself and the environments built from it."""

    def __post_init__(self) -> None:
        BUILT["made"] += 1
        BUILT["alive"] += 1
        BUILT["most_alive"] = max(BUILT["most_alive"], BUILT["alive"])
        weakref.finalize(self, BUILT.subtract, ["alive"])

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        BUILT["envs"] += 1
        return super().make_env(render_mode=render_mode)

    def make_batch_env(self, num_envs: int) -> BatchEnv:
        BUILT["envs"] += 1
        return super().make_batch_env(num_envs)


def _counted(variant: EnvVariant) -> CountedVariant:
    fields = {f.name: getattr(variant, f.name) for f in dataclasses.fields(variant)}
    return CountedVariant(**{**fields, "family": "counted_cartpole"})


def _counted_at(indices: Sequence[int], /, **arguments: Any) -> list[EnvVariant]:
    BUILT["largest_call"] = max(BUILT["largest_call"], len(indices))
    return [_counted(v) for v in FAMILIES["cartpole"].variants_at(indices, **arguments)]  # type: ignore[attr-defined]


SCALE = [
    "env=cartpole",
    "env.family=counted_cartpole",
    "agents=population",
    "agents.num_agents=10000",
    "strategy.participation.mode=uniform",
    "strategy.participation.per_round=1000",
    "rounds=1",
]


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> Iterator[Counter[str]]:
    """The counting family, registered for this test only."""
    monkeypatch.setitem(FAMILIES, "counted_cartpole", LazyFamily(_counted_at))
    BUILT.clear()
    yield BUILT


def test_server_start_up_at_k_10000_holds_no_k_long_list(
    counted: Counter[str], tmp_path: Path
) -> None:
    """fedhpg-server's start-up, up to waiting for its agents: every agent's digest is computed
    (what each hello is checked against) from variants made a chunk at a time and dropped, and
    two environments are built: θ̃_0's policy and the spaces' signature each need one (and one
    more when the config is validated: agent 0's, so a missing simulator fails in one line)."""
    from fedhpg.server.serving import serve

    run = compose([*SCALE, "server.port=0", "server.register_timeout_s=0.2"])
    with pytest.raises(FederationError, match="of 10000 agents registered"):
        serve(run, out_dir=tmp_path / "run", show_progress=False)
    assert counted["made"] >= 10_000, "every agent's digest"
    assert counted["largest_call"] <= ITERATION_CHUNK
    assert counted["most_alive"] <= 2 * ITERATION_CHUNK + 2, "no K-long list held"
    assert counted["envs"] == 3


def test_in_process_pool_at_k_10000_builds_no_agent_up_front(counted: Counter[str]) -> None:
    """The in-process pool holds the K variants (parameters only) and builds an agent's
    worker, and so its environments, when the agent is first asked to train."""
    from fedhpg.server.pools.inprocess import make_in_process_pool

    pool = make_in_process_pool(compose(SCALE))
    try:
        # one when the config was validated, one for the policy's size; none per agent
        assert counted["envs"] == 2
        assert len(pool.agent_ids) == 10_000
        assert counted["largest_call"] == 10_000, "one draw for the pool's variants"
    finally:
        pool.close()


# --- a plugin family that offers only the K-list ------------------------------------------------

LISTED_CALLS: list[int] = []


def listed_cartpole(
    *, seed: int, num_agents: int, level: float, **options: Any
) -> list[EnvVariant]:
    """A plain family (no per-index API), as a plugin written before it existed."""
    LISTED_CALLS.append(num_agents)
    return [
        dataclasses.replace(v, family="listed_cartpole")
        for v in make_variants("cartpole", seed=seed, num_agents=num_agents, level=level, **options)
    ]


@pytest.fixture
def plugins(monkeypatch: pytest.MonkeyPatch) -> None:
    """The list-only family registered, and no K-list cached yet, for this test only."""
    monkeypatch.setitem(FAMILIES, "listed_cartpole", listed_cartpole)
    monkeypatch.setattr(registry, "_EAGER", type(registry._EAGER)())


def _listed_run(num_agents: int) -> RunConfig:
    return compose(
        [
            "env=cartpole",
            "env.family=listed_cartpole",
            "agents=population",
            f"agents.num_agents={num_agents}",
        ]
    )


@pytest.mark.usefixtures("plugins")
def test_a_family_without_the_per_index_api_is_built_once_per_run() -> None:
    LISTED_CALLS.clear()
    run = _listed_run(7)  # composing checks the family: its K-list is made here
    picked = [variant_of(run, k) for k in (6, 0, 3)]
    every = list(run_variants(run))
    assert LISTED_CALLS == [7], "its K-list, once, then cached"
    listed = listed_cartpole(seed=run.seed, num_agents=7, level=run.env.level, gamma=0.999)
    assert picked == [listed[6], listed[0], listed[3]]
    assert every == listed
    variant_of(_listed_run(8), 7)
    assert LISTED_CALLS == [7, 7, 8]


def test_a_family_that_makes_the_wrong_number_of_variants_is_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def short_by_one(*, seed: int, num_agents: int, level: float) -> list[EnvVariant]:
        return make_variants("cartpole", seed=seed, num_agents=num_agents - 1, level=level)

    monkeypatch.setitem(FAMILIES, "short_by_one", short_by_one)
    with pytest.raises(ValueError, match="'short_by_one' made 2 variants, not num_agents=3"):
        make_variant("short_by_one", 0, seed=0, num_agents=3, level=0.5)


def test_a_per_index_plugin_answers_both_calls(monkeypatch: pytest.MonkeyPatch) -> None:
    @per_index_family
    def lengths(index: int, *, seed: int, num_agents: int, level: float) -> EnvVariant:
        length = 0.5 + 0.3 * level * index / num_agents
        return GymVariant(
            family="lengths",
            index=index,
            gamma=0.99,
            params={"length": length},
            env_id="CartPole-v1",
            attributes={"length": length},
        )

    monkeypatch.setitem(FAMILIES, "lengths", lengths)
    every = make_variants("lengths", seed=0, num_agents=5, level=1.0)
    assert [v.params["length"] for v in every] == [0.5 + 0.3 * k / 5 for k in range(5)]
    assert make_variants_at("lengths", [4, 1], seed=0, num_agents=5, level=1.0) == [
        every[4],
        every[1],
    ]
