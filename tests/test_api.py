"""The Python API (``fedhpg.server.commands.api``; its guide's examples run in tests/test_docs.py):
a policy loaded from a run directory reproduces the server's own evaluation in ``summary.json``
exactly; in-process and distributed runs agree; mistakes raise exceptions naming the key."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.commands import api

GRID = ["rounds=3", "seed=1", "eval.every=2", "eval.episodes=6"]


def test_a_loaded_policy_reproduces_a_distributed_runs_summary(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    result = api.run(overrides=GRID, distributed=True, out_dir=out_dir)
    assert torch.equal(result.theta, run_in_process(compose(GRID))), "the same θ̃ as in-process"
    assert [r["round"] for r in result.records] == [1, 2, 3]
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["final_eval_round"] == 3
    policy = api.load_policy(out_dir)
    assert isinstance(policy, torch.nn.Module)
    assert torch.equal(torch.nn.utils.parameters_to_vector(policy.parameters()), result.theta)
    for k in range(4):
        stats = api.evaluate(policy, out_dir, agent=k)
        assert stats.to_json() == summary["eval"][f"agent-{k}"]  # exactly: same streams
    # an earlier evaluation round uses that round's streams: another sample of episodes
    assert api.evaluate(policy, out_dir, agent=0, round=2, episodes=6).episodes == 6
    # acting: the greedy action is the policy's, one observation at a time
    states = torch.arange(25)
    greedy = policy.act(states, None)
    assert [api.act(policy, s) for s in range(25)] == greedy.tolist()
    sampled = api.act(policy, 0, greedy=False, rng=np.random.default_rng(1))
    assert sampled in range(4)


def work(record: dict) -> tuple:
    """What a round computed (its times are measured, so they differ between runs)."""
    agents = [(a["trajectories"], a["env_steps"], a["train_return"]) for a in record["agents"]]
    return record["round"], record["trajectories_per_agent"], agents, record.get("eval")


def test_in_process_run_directory_resumes_and_matches_a_straight_run(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    first = api.run(overrides=[*GRID, "rounds=2"], out_dir=out_dir)
    assert first.out_dir == out_dir and len(first.records) == 2
    assert {p.name for p in out_dir.iterdir()} >= {
        "metrics.jsonl",
        "config.json",
        "summary.json",
        "checkpoints",
        "tensorboard",
    }
    resumed = api.run(overrides=[*GRID, "rounds=4", "resume=true"], out_dir=out_dir)
    straight = api.run(overrides=[*GRID, "rounds=4"])
    assert torch.equal(resumed.theta, straight.theta)
    assert [r["round"] for r in resumed.records] == [1, 2, 3, 4]
    assert [work(r) for r in resumed.records] == [work(r) for r in straight.records]
    # a run directory is not overwritten by a new run
    with pytest.raises(api.ConfigError, match="holds a run already") as info:
        api.run(overrides=GRID, out_dir=out_dir)
    assert info.value.key == "out_dir"


def test_a_config_object_edited_in_python_runs_like_overrides() -> None:
    config = api.compose(GRID)
    config.rounds = 2
    by_object = api.run(config, overrides=["agents.budget.batch_size=[4]"])
    by_overrides = api.run(overrides=[*GRID, "rounds=2", "agents.budget.batch_size=[4]"])
    assert torch.equal(by_object.theta, by_overrides.theta)
    assert [a["trajectories"] for a in by_object.records[0]["agents"]] == [8, 8, 12, 12]


@pytest.mark.parametrize(
    ("config", "overrides", "key"),
    [
        (None, ["rounds=0"], "rounds"),
        (None, ["algo.step_size=fast"], "algo.step_size"),
        ("object", ["algo.step_size=-1"], "algo.step_size"),
        ("object", ["strategy.name=nope"], "strategy.name"),
    ],
)
def test_mistakes_raise_config_errors_naming_the_key(
    config: str | None, overrides: list[str], key: str
) -> None:
    with pytest.raises(api.ConfigError) as info:
        api.run(api.compose(GRID) if config else None, overrides=overrides)
    assert info.value.key == key


def test_misuse_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="in-process runs only"):
        api.run(overrides=GRID, distributed=True, callbacks=[lambda record, theta: None])
    with pytest.raises(api.RunDirectoryError, match=r"config\.json"):
        api.load_policy(tmp_path)
    with pytest.raises(TypeError, match="RunConfig"):
        api.run({"rounds": 2})  # type: ignore[arg-type]
