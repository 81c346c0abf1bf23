"""Extension points from outside the package: a test module registers an algorithm and a
strategy (``fedhpg_toy_plugin``), and a real ``fedhpg-run`` federation runs them."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from procs import processes, start

from fedhpg.common.config import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.pools.inprocess import run_in_process

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


def test_a_plugin_algorithm_and_strategy_run_through_fedhpg_run(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    os.environ["PYTHONPATH"] = f"{TESTS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"
    try:
        with processes() as started:
            launcher = start(
                started,
                "fedhpg-run",
                [*OVERRIDES, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'h'}"],
                cwd=tmp_path,
            )
            stdout, stderr = launcher.communicate(timeout=180)
    finally:
        os.environ["PYTHONPATH"] = os.environ["PYTHONPATH"].split(os.pathsep, 1)[1]
    assert launcher.returncode == 0, stderr[-3000:]
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


def test_plugin_options_are_checked_by_name() -> None:
    with pytest.raises(ConfigError, match="must be > 0") as info:
        run_in_process(compose([*OVERRIDES, "algo.params.scale=-1"]))
    assert info.value.key == "algo.params.scale"
