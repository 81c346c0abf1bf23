"""Extension points from outside the package: test modules register an algorithm and a
strategy (``fedhpg_toy_plugin``), an environment family and a policy
(``fedhpg_toy_env_plugin``), and real ``fedhpg-run`` federations run them; families and
policies are also found by dotted path and through an installed package's entry points."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch
from procs import processes, start

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.learning.group import EngineGroup, make_agent_group
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.registry import make_variants
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api

TESTS = Path(__file__).parent
OVERRIDES = [
    "plugins=[fedhpg_toy_plugin]",
    "algo.name=toy_sign",
    "+algo.params.scale=0.05",
    "++agents.budget.steps=[1,2,3]",
    "strategy.name=toy_alternate",
    "rounds=4",
    "seed=2",
    "agents.num_agents=3",
    "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]",  # demo4 has four; the plugin ignores it
    "agents.speeds=[1]",
    "agents.step_delays_s=[0]",
    "eval.every=2",
    "eval.episodes=4",
]


@contextmanager
def plugins_on_pythonpath() -> Iterator[None]:
    """The plugin modules importable by the child processes too."""
    os.environ["PYTHONPATH"] = f"{TESTS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"
    try:
        yield
    finally:
        os.environ["PYTHONPATH"] = os.environ["PYTHONPATH"].split(os.pathsep, 1)[1]


def fedhpg_run(overrides: list[str], tmp_path: Path) -> tuple[Path, str]:
    out_dir = tmp_path / "run"
    with plugins_on_pythonpath(), processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*overrides, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'h'}"],
            cwd=tmp_path,
        )
        stdout, stderr = launcher.communicate(timeout=180)
    assert launcher.returncode == 0, stderr[-3000:]
    return out_dir, stdout


@pytest.mark.alongside  # fedhpg-run on a free port with the defaults' waits, checked by its outputs
def test_a_plugin_algorithm_and_strategy_run_through_fedhpg_run(tmp_path: Path) -> None:
    out_dir, stdout = fedhpg_run(OVERRIDES, tmp_path)
    assert "B=4" not in stdout and "batch_size=4 steps=2" in stdout, "the plugin's budget label"
    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    # the strategy's select: every agent in odd rounds, the even-indexed ones in even rounds
    assert [[a["index"] for a in r["agents"]] for r in records] == [[0, 1, 2], [0, 2]] * 2
    # the algorithm's budget and its own statistic reached metrics.jsonl
    assert [a["trajectories"] for a in records[0]["agents"]] == [4, 8, 12]
    assert all(0.0 <= a["sign_flips"] <= 1.0 for r in records for a in r["agents"])
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 4
    assert torch.equal(checkpoint.theta, run_in_process(compose(OVERRIDES)))


@pytest.mark.alongside  # fedhpg-run on a free port with the defaults' waits, checked by its outputs
def test_a_plugin_algorithm_runs_batched_for_a_thousand_agents_on_two_hosts(
    tmp_path: Path,
) -> None:
    """The plugin's algorithm, written with the engine's primitives and nothing else, trains
    1,000 CartPole agents as two hosts of 500 rows each (one batch per host and iteration), and
    ends with the θ̃ the in-process pool computes for the same 1,000 agents in one batch."""
    overrides = [
        "plugins=[fedhpg_toy_plugin]", "env=cartpole", "algo.name=toy_sign",
        "+algo.params.scale=0.01", "++agents.budget.steps=[2]", "agents=population",
        "agents.num_agents=1000", "agents.per_host=500", "agents.clock=counted", "rounds=2",
        "eval.every=2", "eval.episodes=1", "server.tensorboard=false",
    ]  # fmt: skip
    run = compose(overrides)
    assert isinstance(make_agent_group(run, list(range(500))), EngineGroup), "batched"
    out_dir, _ = fedhpg_run(overrides, tmp_path)
    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert [len(r["agents"]) for r in records] == [1000, 1000]
    assert all(0.0 <= a["sign_flips"] <= 1.0 for r in records for a in r["agents"])
    batches = {a["trajectories"] for a in records[0]["agents"]}
    assert batches == {8, 16, 32}, "each agent's own B_k (4, 8 or 16) twice"
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and torch.equal(checkpoint.theta, run_in_process(run))


def test_plugin_options_are_checked_by_name() -> None:
    with pytest.raises(ConfigError, match="must be > 0") as info:
        run_in_process(compose([*OVERRIDES, "algo.params.scale=-1"]))
    assert info.value.key == "algo.params.scale"


def test_a_strategy_declares_the_updates_it_takes_and_whether_rounds_may_be_buffered(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """No strategy or algorithm is named in a check: a strategy of a kind of update of its own
    (``takes``) runs only with an algorithm that sends that kind (one that names it,
    ``Algorithm.strategy``), and one that is not ``buffered`` refuses buffered rounds."""
    from fedhpg_toy_plugin import ToySign

    from fedhpg.common.learning.algorithms import ALGORITHMS
    from fedhpg.server.assembly import check_run
    from fedhpg.server.strategies import STRATEGIES, CoordinateRule, NoParams

    class Deltas(CoordinateRule[NoParams]):
        name = "toy_deltas"
        takes = "deltas"
        buffered = False

        def combine(self, rows: torch.Tensor) -> torch.Tensor:
            return rows.mean(dim=0)

    class SendsDeltas(ToySign):
        name = "toy_sends_deltas"
        strategy = "toy_deltas"
        sends = "deltas"

    ALGORITHMS.names(), STRATEGIES.names()  # the package's own entries first
    monkeypatch.setitem(ALGORITHMS._entries, SendsDeltas.name, SendsDeltas())
    monkeypatch.setitem(STRATEGIES._entries, Deltas.name, Deltas)
    toy = ("algo.name", "+algo.params", "++agents.budget", "strategy.name")
    common = [o for o in OVERRIDES if not o.startswith(toy)]
    with pytest.raises(ConfigError) as info:
        check_run(compose([*common, "strategy.name=toy_deltas"]), distributed=False)
    assert info.value.key == "strategy"
    assert "toy_deltas aggregates deltas: it runs with an algorithm that sends them " in str(
        info.value
    )
    assert "(algo=toy_sends_deltas), not algo=fedhpg, which sends parameters" in str(info.value)
    toy_algorithm = [o for o in OVERRIDES if o.startswith(toy[:3])]
    sends_deltas = [o.replace("toy_sign", SendsDeltas.name) for o in toy_algorithm]
    paired = [*common, *sends_deltas, "strategy.name=toy_deltas"]
    with pytest.raises(ConfigError) as info:
        check_run(compose([*paired, "server.round_policy=buffered"]), distributed=False)
    assert info.value.key == "server.round_policy" and "strategy=toy_deltas" in str(info.value)
    result = api.run(overrides=[*paired, "rounds=1"])
    assert [r["round"] for r in result.records] == [1]


ENV_PLUGIN = "fedhpg_toy_env_plugin"
TOY_RUN = [
    "env=cartpole",  # the CartPole preset's learning settings; its family options are cartpole's
    "~env.options.gamma",
    "agents=homogeneous4",
    "agents.num_agents=3",
    "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[2]",
    "algo.step_size=0.1",
    "rounds=3",
    "seed=4",
    "eval.every=3",
    "eval.episodes=3",
]
BY_NAME = [f"plugins=[{ENV_PLUGIN}]", "env.family=short_cartpoles", "policy.name=linear_softmax"]
BY_PATH = [
    f"env.family={ENV_PLUGIN}:short_cartpoles",
    f"policy.name={ENV_PLUGIN}:LinearSoftmaxPolicy",
]


@pytest.mark.alongside  # fedhpg-run on a free port with the defaults' waits, checked by its outputs
def test_a_plugin_env_family_and_policy_run_through_fedhpg_run(tmp_path: Path) -> None:
    out_dir, _ = fedhpg_run([*TOY_RUN, *BY_NAME], tmp_path)
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 3
    # the plugin's policy: W [2, 4] and b [2] on CartPole (the built-in MLP has 4610)
    assert checkpoint.theta.numel() == 10
    # the plugin's variants, generated by the server and by every forked agent
    summary = json.loads((out_dir / "summary.json").read_text())
    from fedhpg_toy_env_plugin import STEP_LIMIT, short_cartpoles

    expected = short_cartpoles(seed=4, num_agents=3, level=0.5)
    for k, variant in enumerate(expected):
        assert summary["variants"][f"agent-{k}"]["toy_length"] == variant.params["toy_length"]
    assert len({v["toy_length"] for v in summary["variants"].values()}) == 3
    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert max(r["eval"]["agent-0"]["length_mean"] for r in records if "eval" in r) <= STEP_LIMIT
    # the same federation in this process, the plugin named by dotted paths: the same θ̃
    assert torch.equal(checkpoint.theta, run_in_process(compose([*TOY_RUN, *BY_PATH])))


def test_an_installed_packages_entry_points_offer_a_family_and_a_policy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A distribution's metadata as pip installs it, on sys.path: importlib.metadata finds it.
    info = tmp_path / "site" / "toy_fedhpg_plugin-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-fedhpg-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        f"[fedhpg.env_families]\ntoy_installed = {ENV_PLUGIN}:short_cartpoles\n"
        f"[fedhpg.policies]\ntoy_installed_linear = {ENV_PLUGIN}:LinearSoftmaxPolicy\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    variants = make_variants("toy_installed", seed=4, num_agents=3, level=0.5)
    assert [v.params for v in variants] == [
        v.params for v in run_variants(compose([*TOY_RUN, *BY_PATH]))
    ]
    installed = ["env.family=toy_installed", "policy.name=toy_installed_linear"]
    result = api.run(overrides=[*TOY_RUN, *installed])
    assert torch.equal(result.theta, run_in_process(compose([*TOY_RUN, *BY_PATH])))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("env.family=no_such_family", "unknown environment family 'no_such_family'"),
        ("env.family=no_such_module:factory", "cannot import environment family"),
        ("policy.name=no_such_policy", "no policy 'no_such_policy'"),
        ("policy.name=fedhpg_toy_env_plugin:missing", "cannot import"),
    ],
)
def test_unknown_families_and_policies_are_named(override: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        run_in_process(compose([*TOY_RUN, override]))


def test_a_policy_that_is_no_policy_subclass_is_refused() -> None:
    with pytest.raises(ConfigError, match="not a fedhpg Policy subclass") as info:
        run_in_process(compose([*TOY_RUN, f"policy.name={ENV_PLUGIN}:not_a_policy"]))
    assert info.value.key == "policy.name"


@pytest.mark.parametrize(
    ("env", "name"),
    [("gridworld", "tabular"), ("cartpole", "mlp_categorical"), ("pendulum", "gaussian_mlp")],
)
def test_built_in_policies_by_name_are_the_auto_choice_bit_for_bit(env: str, name: str) -> None:
    from fedhpg.common.learning.worker import initial_theta

    run = compose([f"env={env}", "agents=homogeneous4"])
    variant = run_variants(run)[0]
    auto = initial_theta(variant, run)
    named = initial_theta(
        variant, compose([f"env={env}", "agents=homogeneous4", f"policy.name={name}"])
    )
    assert run.policy.name == "auto" and torch.equal(auto, named)
    wrong = "gaussian_mlp" if name != "gaussian_mlp" else "mlp_categorical"
    with pytest.raises(ConfigError, match=f"policy '{wrong}' needs"):
        initial_theta(
            variant, compose([f"env={env}", "agents=homogeneous4", f"policy.name={wrong}"])
        )
