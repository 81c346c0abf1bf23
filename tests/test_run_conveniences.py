"""What a run directory offers besides the rounds: stopping at a target return
(``eval.stop_at``), the best evaluation's checkpoint (``checkpoint.keep_best``), every N-th
round's checkpoint (``checkpoint.every``)."""

from __future__ import annotations

import json
import logging
import os
import subprocess
from pathlib import Path

import pytest
import torch

from fedhpg.server.checkpoint import BEST_NAME, KEPT_DIR, load_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.run_dir import RunDirectoryError, claimed
from tests.procs import BIN, QUIET

SHORT = ["rounds=6", "eval.every=2", "eval.episodes=2", "agents.virtual_clock=true"]
REACHED = "eval.stop_at=-1000"  # any evaluation reaches it: the run stops at round 2


def _summary(out_dir: Path) -> dict:
    return json.loads((out_dir / "summary.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("policy", ["wait_all", "buffered"])
def test_a_run_stops_after_the_evaluation_that_reaches_the_target(
    tmp_path: Path, policy: str
) -> None:
    out_dir = tmp_path / "run"
    result = api.run(overrides=[*SHORT, REACHED, f"server.round_policy={policy}"], out_dir=out_dir)
    assert [r["round"] for r in result.records] == [1, 2]
    summary = _summary(out_dir)
    assert summary["stopped_early"] == {"round": 2, "stop_at": -1000.0}
    assert summary["final_eval_round"] == 2
    assert result.last_evaluation is not None


def test_a_target_not_reached_runs_every_round(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    result = api.run(overrides=[*SHORT, "rounds=2", "eval.stop_at=1e9"], out_dir=out_dir)
    assert [r["round"] for r in result.records] == [1, 2]
    assert _summary(out_dir)["stopped_early"] is None


def test_fedhpg_run_stops_early_with_exit_0_and_its_final_table(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    done = subprocess.run(
        [BIN / "fedhpg-run", *SHORT, REACHED, f"server.out_dir={out_dir}", "server.port=0"],
        cwd=tmp_path,
        env={**os.environ, **QUIET},
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr
    assert "Unified policy after round 2" in done.stdout
    assert _summary(out_dir)["stopped_early"]["round"] == 2
    lines = (out_dir / "metrics.jsonl").read_text(encoding="utf-8").splitlines()
    assert len(lines) == 2


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("eval.stop_at=nan", "eval.stop_at"),
        ("checkpoint.every=0", "checkpoint.every"),
    ],
)
def test_a_bad_value_is_one_line_naming_its_key(tmp_path: Path, override: str, key: str) -> None:
    done = subprocess.run(
        [BIN / "fedhpg-run", override],
        cwd=tmp_path,
        env={**os.environ, **QUIET},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert key in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_best_evaluations_checkpoint_is_kept_and_loads(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    keys = [*SHORT, "checkpoint.keep_best=true", "checkpoint.every=2"]
    result = api.run(overrides=keys, out_dir=out_dir)
    returns = {
        r["round"]: sum(e["return_mean"] for e in r["eval"].values()) / len(r["eval"])
        for r in result.records
        if r.get("eval")
    }
    best_round = max(returns, key=lambda r: (returns[r], -r))  # the first of the best
    summary = _summary(out_dir)["best"]
    assert summary["round"] == best_round
    assert summary["return_mean"] == pytest.approx(returns[best_round])
    best = load_checkpoint(out_dir / "checkpoints" / BEST_NAME)
    assert best.round == best_round
    policy = api.load_policy(out_dir, best=True)
    theta = torch.nn.utils.parameters_to_vector(policy.parameters())
    assert torch.equal(theta, best.theta)
    newest = torch.nn.utils.parameters_to_vector(api.load_policy(out_dir).parameters())
    assert torch.equal(newest, result.theta)  # the newest stays the default
    # checkpoint.every=2: rounds 2, 4, 6 kept besides the rolling newest two
    names = sorted(p.name for p in (out_dir / "checkpoints").glob("round-*"))
    assert names == ["round-000005.safetensors", "round-000006.safetensors"]
    kept = sorted(p.name for p in (out_dir / "checkpoints" / KEPT_DIR).iterdir())
    assert kept == [f"round-00000{r}.safetensors" for r in (2, 4, 6)]
    assert load_checkpoint(out_dir / "checkpoints" / KEPT_DIR / kept[0]).round == 2


def test_without_keep_best_there_is_no_best_to_load(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*SHORT, "rounds=1"], out_dir=out_dir)
    assert sorted(p.name for p in (out_dir / "checkpoints").iterdir()) == [
        "round-000001.safetensors"
    ]
    assert "best" not in _summary(out_dir)
    with pytest.raises(RunDirectoryError, match=r"checkpoint\.keep_best=true"):
        api.load_policy(out_dir, best=True)


def test_the_servers_log_lines_go_to_run_log_beside_metrics(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*SHORT, REACHED], out_dir=out_dir)
    log = (out_dir / "run.log").read_text(encoding="utf-8")
    assert "INFO fedhpg.server.coordinator: round 2: mean evaluation return" in log
    api.run(overrides=[*SHORT, "resume=true"], out_dir=out_dir)
    resumed = (out_dir / "run.log").read_text(encoding="utf-8")
    assert resumed.startswith(log) and "resuming" in resumed[len(log) :]  # appended


def test_a_start_that_fails_before_its_first_round_leaves_no_run_log(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    with pytest.raises(RuntimeError), claimed(out_dir, resume=False):
        logging.getLogger("fedhpg.server").info("starting")
        assert "starting" in (out_dir / "run.log").read_text(encoding="utf-8")
        raise RuntimeError("a start that fails")
    assert not out_dir.exists()
    files = [getattr(h, "baseFilename", "") for h in logging.getLogger().handlers]
    assert not [name for name in files if name.endswith("run.log")]  # the handler is gone
