"""What a run directory offers besides the rounds: stopping at a target return
(``eval.stop_at``), the best evaluation's checkpoint (``checkpoint.keep_best``), every N-th
round's checkpoint (``checkpoint.every``)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from fedhpg.server import api
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
