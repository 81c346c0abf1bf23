"""The open vocabularies: a module of its own registers an attack, an estimator, a baseline, a
clock and a round policy, and runs them through the public API (in process, short
federations, fixed seeds). Each entry only declares behaviour, so each run is checked against
the built-in choice that declares the same, bit for bit, or against the exact property its
declaration promises."""

from __future__ import annotations

from typing import Any

import pytest
import torch

from fedhpg.common.configuration.config import RunConfig, validate
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.attack import AttackConfig
from fedhpg.common.configuration.vocabularies import (
    ATTACKS,
    BASELINES,
    CLOCKS,
    ESTIMATORS,
    ROUND_POLICIES,
    Attack,
    Baseline,
    Clock,
    Estimator,
    RoundPolicy,
    UpdateToCorrupt,
)
from fedhpg.common.learning import estimators
from fedhpg.common.learning.attacks import corrupt_rows
from fedhpg.common.learning.staircase import Staircase
from fedhpg.server.commands import api
from fedhpg.server.coordinator import RoundRecord


def _start_plus_one(update: UpdateToCorrupt) -> torch.Tensor:
    """Sends θ̃ + 1 on every coordinate, whatever the agent learnt."""
    return update.start + 1.0


ATTACKS.register("test_start_plus_one")(Attack(corrupt=_start_plus_one))
ATTACKS.register("test_faulty_actuator")(Attack(acts_randomly=True))
ESTIMATORS.register("test_whole_return")(Estimator(per_step=False))
BASELINES.register("test_leave_one_out")(Baseline(subtracts_mean=True))
CLOCKS.register("test_priced")(Clock(counts_work=True))
ROUND_POLICIES.register("test_quorum")(RoundPolicy(quorum=True))

SHORT = [
    "rounds=2", "env.family=cartpole", "agents.num_agents=3", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "algo.step_size=0.01", "eval.every=2", "eval.episodes=2", "server.tensorboard=false",
    "seed=5",
]  # fmt: skip
COUNTED = ["agents.virtual_clock=true", "server.tensorboard=false", "seed=3", "rounds=3"]


def _thetas(overrides: list[str]) -> list[torch.Tensor]:
    """θ_k every agent sent in each round, then θ̃_T."""
    records: list[RoundRecord] = []
    result = api.run(overrides=overrides, callbacks=[lambda r, _: records.append(r)])
    sent = [torch.from_numpy(r.result.thetas.copy()) for r in records]
    return [*sent, result.theta]


def test_a_registered_name_is_taken_once_and_listed_after_the_built_in_ones() -> None:
    with pytest.raises(ValueError, match="already registered"):
        ATTACKS.register("sign_flip")(Attack(corrupt=_start_plus_one))
    assert ATTACKS.names()[:3] == ["none", "zero_gradient", "random_noise"]
    assert ATTACKS.names()[-1] in ("test_start_plus_one", "test_faulty_actuator")
    validate(RunConfig(attack=AttackConfig(kind="test_start_plus_one", agents=[0])))
    with pytest.raises(ConfigError, match=r"attack\.kind: got 'lies', allowed: none, zero_"):
        validate(RunConfig(attack=AttackConfig(kind="lies")))


def test_a_registered_update_attack_sends_what_it_declares() -> None:
    start, honest = torch.zeros(5), torch.randn(2, 5, generator=torch.Generator().manual_seed(0))
    attack = AttackConfig(kind="test_start_plus_one", agents=[7])
    rows = corrupt_rows(attack, start, honest, [3, 7], seed=0, round_index=1)
    assert torch.equal(rows[0], honest[0]), "the honest agent's row is untouched"
    assert torch.equal(rows[1], torch.ones(5))


def test_a_registered_update_attack_runs_in_a_federation() -> None:
    """Agent 1 sends θ̃ + 1; 'zero_gradient' shows θ̃ (it sends θ̃ back); the others are honest."""
    honest = _thetas(SHORT)
    attacked = _thetas([*SHORT, "attack.kind=test_start_plus_one", "attack.agents=[1]"])
    start = _thetas([*SHORT, "attack.kind=zero_gradient", "attack.agents=[1]"])[0][1]
    assert torch.equal(attacked[0][1], start + 1.0)
    assert torch.equal(attacked[0][0], honest[0][0]) and torch.equal(attacked[0][2], honest[0][2])
    assert not torch.equal(attacked[-1], honest[-1]), "the attacker moved θ̃"


def test_a_registered_sampling_attack_is_read_from_its_declaration() -> None:
    """Declared to act at random while sampling, as 'random_action' is: the same rows."""
    keys = [*SHORT, "attack.agents=[1]"]
    built_in = _thetas([*keys, "attack.kind=random_action"])
    registered = _thetas([*keys, "attack.kind=test_faulty_actuator"])
    assert all(torch.equal(a, b) for a, b in zip(built_in, registered, strict=True))
    assert not torch.equal(_thetas(SHORT)[0][1], registered[0][1])


def test_a_registered_estimator_and_baseline_run_as_they_declare() -> None:
    """Whole-trajectory credit with a leave-one-out mean: REINFORCE with the mean baseline."""
    registered = _thetas(
        [*SHORT, "algo.estimator=test_whole_return", "algo.baseline=test_leave_one_out"]
    )
    built_in = _thetas([*SHORT, "algo.estimator=reinforce", "algo.baseline=mean"])
    assert all(torch.equal(a, b) for a, b in zip(built_in, registered, strict=True))
    assert not torch.equal(_thetas(SHORT)[-1], registered[-1]), "GPOMDP (the default) differs"
    layout = Staircase.padded(3, 4, torch.device("cpu"))
    rewards = torch.arange(12, dtype=torch.float64)
    coef = estimators.coefficients(
        "test_whole_return", layout, rewards, None, gamma=0.9, baseline="test_leave_one_out"
    )
    assert torch.equal(coef, estimators.coefficients("reinforce", layout, rewards, None, gamma=0.9))
    with pytest.raises(ConfigError, match=r"needs algo\.estimator=gpomdp"):
        validate(_run_of(["algo.estimator=test_whole_return", "algo.reward_to_go=from_step"]))


def _run_of(overrides: list[str]) -> RunConfig:
    return api.resolve_config(overrides=overrides)


def test_a_registered_clock_and_round_policy_run_as_they_declare() -> None:
    """A clock that counts work is the counted clock; a quorum policy closes rounds as
    'deadline' does: the slowest agent (speed 0.25) is cut, on the emulated clock."""
    deadline = ["server.round_deadline_s=0.7"]
    built_in = api.run(
        overrides=[*COUNTED, "agents.clock=counted", "server.round_policy=deadline", *deadline]
    )
    registered = api.run(
        overrides=[*COUNTED, "agents.clock=test_priced", "server.round_policy=test_quorum",
                   *deadline]
    )  # fmt: skip
    assert torch.equal(built_in.theta, registered.theta)
    for record in registered.records:
        assert all(a["emulated_s"] <= 0.7 for a in record["agents"])
        assert record["stragglers"] == ["agent-3"]

    def emulated(records: list[dict[str, Any]]) -> list[list[float]]:
        return [[a["emulated_s"] for a in r["agents"]] for r in records]

    assert emulated(registered.records) == emulated(built_in.records)
