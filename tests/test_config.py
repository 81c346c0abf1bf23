"""Configuration: composition, validation, and one-line errors with exit status 2."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from fedhpg.common.configuration.config import RunConfig, from_dict, to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_keys import fixed_difference, unknown_key
from fedhpg.common.configuration.run_roles import GROUPS
from fedhpg.common.configuration.settings.agents import AgentsConfig
from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.learning.components import agent_profile, validate_run
from fedhpg.common.runtime.cli import compose, compose_sweep, repeated_key


def test_default_config_composes_and_validates() -> None:
    run = compose([])
    assert run.agents.num_agents == 4
    assert run.env.family == "gridworld"


def test_overrides_apply() -> None:
    run = compose(
        [
            "rounds=3",
            "agents.num_agents=2",
            "agents.budget.batch_size=[4,6]",
            "agents.budget.local_iters=[1]",
            "agents.speeds=[1]",
            "agents.step_delays_s=[0]",
        ]
    )
    assert (run.rounds, run.agents.num_agents, run.agents.budget["batch_size"]) == (3, 2, [4, 6])


def test_per_agent_lists_must_match_the_agent_count() -> None:
    with pytest.raises(ConfigError, match="needs 1 or num_agents=2 values"):
        compose(["agents.num_agents=2"])


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["agents.budget.batch_size=[0]"], "agents.budget.batch_size[0]"),
        (["agents.budget.batch_size=[4,5]"], "agents.budget.batch_size"),
        (["agents.budget.local_iters=[1.5]"], "agents.budget.local_iters[0]"),
        (["++agents.budget.batch_szie=[4]"], "agents.budget.batch_szie"),
        (["algo.name=nope"], "algo.name"),
        (["algo.step_size=-1"], "algo.step_size"),
        (["algo.step_size=fast"], "algo.step_size"),
        (["rounds=many"], "rounds"),
        (["algo=fedhpgvr", "algo.params.iw_clip=[2.0,1.0]"], "algo.params.iw_clip"),
        (["algo=fedhpgvr", "algo.params.iw_mode=sometimes"], "algo.params.iw_mode"),
        (
            ["algo=fedhpgvr", "algo.estimator=reinforce", "algo.params.iw_mode=per_decision"],
            "algo.params.iw_mode",
        ),
        (["algo=fedhpgvr", "+algo.params.iw_kind=1"], "algo.params.iw_kind"),
        (["algo=fedhpgvr", "agents.budget.inner_steps=[0]"], "agents.budget.inner_steps[0]"),
        (
            ["algo=fedhpgvr", "agents.budget.mini_batch_size=[0]"],
            "agents.budget.mini_batch_size[0]",
        ),
        (["attack.kind=sign_flip", "attack.agents=[9]"], "attack.agents[0]"),
        (["attack.kind=lies"], "attack.kind"),
        (["plugins=[no_such_fedhpg_plugin]"], "plugins[0]"),
        (["no_such_key=1"], "no_such_key"),
        (["env.level=2"], "env.level"),
        (["eval.horizon=0"], "eval.horizon"),
    ],
)
def test_bad_values_name_the_key(overrides: list[str], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        compose(overrides)
    assert info.value.key == key, str(info.value)


def test_unknown_algorithm_lists_the_known_ones() -> None:
    with pytest.raises(ConfigError, match="known: fedhpg, fedhpgvr"):
        validate_run(RunConfig(algo=AlgoConfig(name="nope")))


def test_dict_round_trip() -> None:
    run = RunConfig(
        agents=AgentsConfig(num_agents=2, speeds=[1.0, 0.25], budget={"batch_size": [3]})
    )
    assert from_dict(to_dict(run)) == run


def test_one_value_applies_to_every_agent() -> None:
    run = RunConfig(
        agents=AgentsConfig(num_agents=3, budget={"batch_size": [7], "local_iters": [1, 2, 3]})
    )
    assert [agent_profile(run, k).budget.batch_size for k in range(3)] == [7, 7, 7]
    assert [agent_profile(run, k).budget.local_iters for k in range(3)] == [1, 2, 3]


def test_a_budget_takes_the_algorithms_defaults_and_ignores_other_algorithms_keys() -> None:
    """demo4 sets FedHPG's local_iters; FedHPGVR takes batch_size, its own N and b_k."""
    run = compose(["algo=fedhpgvr"])
    budget = agent_profile(run, 3).budget
    assert (budget.batch_size, budget.inner_steps, budget.mini_batch_size) == (20, 3, 5)
    assert run.agents.budget["local_iters"] == [2, 2, 3, 3]


def test_every_config_key_has_one_declared_role() -> None:
    assert list(GROUPS) == [f.name for f in dataclasses.fields(RunConfig)]


@pytest.mark.parametrize("script", ["fedhpg-run", "fedhpg-server", "fedhpg-agent"])
def test_console_scripts_exit_2_with_one_line(script: str) -> None:
    executable = f"{sys.prefix}/bin/{script}"
    result = subprocess.run(
        [executable, "agents.budget.batch_size=[0]"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2, result.stderr
    assert "agents.budget.batch_size[0]" in result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_the_config_module_imports_no_heavy_library() -> None:
    """Every process imports the config first: it must not pull torch, zmq or gymnasium
    (import-linter checks the static imports; this checks what really gets loaded)."""
    probe = (
        "import sys, fedhpg.common.configuration.config, fedhpg.common.configuration.registry, "
        "fedhpg.common.records.types, fedhpg.common.configuration.vocabularies, "
        "fedhpg.common.configuration.run_keys, fedhpg.common.configuration.run_roles, "
        "fedhpg.common.configuration.placement; "
        "print([m for m in ('torch', 'zmq', 'gymnasium', 'hydra') if m in sys.modules])"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_an_unknown_key_names_the_nearest_known_one() -> None:
    assert unknown_key({"rouds": 3}) == "rouds: not a fedhpg key; did you mean rounds?"
    assert unknown_key({"algo": {"stepsize": 1}}) == (
        "algo.stepsize: not a fedhpg key; did you mean algo.step_size?"
    )
    assert unknown_key({"round_timeout_s": 1}) == (
        "round_timeout_s: not a fedhpg key; did you mean server.round_timeout_s?"
    )
    assert unknown_key({"foo": 1}) == "foo: not a fedhpg key"
    free = {"env": {"options": {"any": 1}}, "algo": {"params": {"x": 1}}}
    assert unknown_key(free) is None, "registry entries check their own options"
    assert unknown_key(to_dict(compose([]))) is None


def test_a_resume_names_the_exact_fixed_key_that_changed() -> None:
    run = to_dict(compose(["algo.step_size=0.5"]))
    changed = fixed_difference(run, to_dict(compose(["algo.step_size=0.1"])))
    assert changed is not None and changed.key == "algo.step_size"
    assert "the run has 0.5, this invocation 0.1" in str(changed)
    may_change = compose(["algo.step_size=0.5", "rounds=90", "eval.every=2", "server.port=7"])
    assert fixed_difference(run, to_dict(may_change)) is None


def test_a_sweep_is_checked_point_by_point() -> None:
    runs = compose_sweep(["seed=0,1", "agents.budget.batch_size=[8],[4,5,6,7]"])
    assert [(r.seed, r.agents.budget["batch_size"]) for r in runs] == [
        (0, [8]), (0, [4, 5, 6, 7]), (1, [8]), (1, [4, 5, 6, 7]),
    ]  # fmt: skip
    with pytest.raises(ConfigError, match=r"sweep point 2/2 \(env.family=foo\)") as error:
        compose_sweep(["env.family=gridworld,foo"])
    assert error.value.key == "sweep point 2/2 (env.family=foo): env.family"


def test_an_integer_beyond_64_bits_is_refused_by_its_key() -> None:
    with pytest.raises(ConfigError) as error:
        compose([f"rounds={10**30}"])
    assert error.value.key == "rounds"
    with pytest.raises(ConfigError) as error:
        compose([f"agents.budget.batch_size=[4,{2**63}]"])
    assert error.value.key == "agents.budget.batch_size[1]"
    assert compose([f"seed={2**63 - 1}"]).seed == 2**63 - 1


def test_a_key_typed_twice_with_different_values_is_refused() -> None:
    """The rule every entry point applies to its own argv, as typed."""
    for args, key, first, second in [
        (["rounds=3", "rounds=4"], "rounds", "rounds=3", "rounds=4"),
        (["env=cartpole", "env=acrobot"], "env", "env=cartpole", "env=acrobot"),
        (["+algo.step_size=0.1", "algo.step_size=0.2"], "algo.step_size", "+algo.step_size=0.1",
         "algo.step_size=0.2"),
        (["-m", "seed=0,1", "rounds=3", "seed=2"], "seed", "seed=0,1", "seed=2"),
        (["hydra.run.dir=a", "hydra.run.dir=b"], "hydra.run.dir", "hydra.run.dir=a",
         "hydra.run.dir=b"),
    ]:  # fmt: skip
        error = repeated_key(args)
        assert error is not None, args
        assert str(error) == f"{key}: given twice ({first}, {second}); give it once"
    # the same value twice loses nothing; flags, their values and deletions are no keys
    assert repeated_key(["server.out_dir=run", "rounds=3", "server.out_dir=run"]) is None
    assert repeated_key(["--cfg", "job", "-cn", "config", "~eval.stop_at", "rounds=3"]) is None


def test_a_programs_own_list_of_overrides_keeps_hydras_last_wins() -> None:
    """compose (and the Python API on it) takes a list a program built, where appending an
    override to replace a base one is deliberate."""
    assert compose(["rounds=3", "rounds=4"]).rounds == 4
    assert compose(["env=cartpole", "env=acrobot"]).env.family == "acrobot"
