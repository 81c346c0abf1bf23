"""The logs people read a run with, each read back with its own tool: ``progress.csv`` with
the csv module, Weights & Biases' offline run file record by record (``server.wandb=true``,
``WANDB_MODE=offline``), and one run-directory convention for every entry point."""

from __future__ import annotations

import csv
import json
import os
import re
import struct
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from procs import BIN

from fedhpg.common.runtime.cli import compose
from fedhpg.server.checkpoint import checkpoint_path
from fedhpg.server.commands import api
from fedhpg.server.run_dir import new_run_dir

RUN = ["rounds=4", "seed=3", "eval.every=2", "eval.episodes=4", "agents=homogeneous4"]


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def test_progress_csv_has_a_row_per_round_with_the_metrics_values(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    result = api.run(overrides=RUN, out_dir=out_dir)
    rows = _csv(out_dir / "progress.csv")
    assert [int(r["round"]) for r in rows] == [1, 2, 3, 4]
    for row, record in zip(rows, result.records, strict=True):
        assert float(row["round_time_s"]) == pytest.approx(record["round_time_s"], rel=1e-5)
        assert float(row["trajectories_per_agent"]) == pytest.approx(
            record["trajectories_per_agent"], rel=1e-5
        )
        returns = [a["train_return"] for a in record["agents"]]
        assert float(row["train_return_mean"]) == pytest.approx(
            sum(returns) / len(returns), rel=1e-5, abs=1e-6
        )
        if "eval" in record:
            evaluated = [e["return_mean"] for e in record["eval"].values()]
            assert float(row["eval_return_min"]) == pytest.approx(min(evaluated), abs=1e-6)
            assert row["eval_success_mean"] != "", "GridWorld has a goal"
        else:
            assert row["eval_return_mean"] == "" and row["eval_return_min"] == ""


def test_a_resumed_run_keeps_its_rows_once(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN[1:], "rounds=3"], out_dir=out_dir)
    checkpoint_path(out_dir / "checkpoints", 3).unlink()  # resume from round 2
    api.run(overrides=[*RUN, "resume=true"], out_dir=out_dir)
    assert [int(r["round"]) for r in _csv(out_dir / "progress.csv")] == [1, 2, 3, 4]


def test_no_success_column_without_a_goal(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=["env=cartpole", *RUN, "agents.budget.batch_size=[2]"], out_dir=out_dir)
    assert "eval_success_mean" not in _csv(out_dir / "progress.csv")[0]


# --- Weights & Biases, offline --------------------------------------------------------------


def wandb_records(path: Path) -> Iterator[bytes]:
    """The records of a W&B run file (``run-<id>.wandb``): a 7-byte header (":W&B", a magic,
    a version), then LevelDB's log format: 32 KiB blocks of records, each a 7-byte header
    (CRC, length, type: full, or first, middle, last part) and its bytes."""
    data = path.read_bytes()
    assert data[:4] == b":W&B", "not a W&B run file"
    block, position, parts = 32768, 7, b""
    while position + 7 <= len(data):
        left = block - position % block
        if left < 7:  # a block's tail too short for a header is padding
            position += left
            continue
        _, length, kind = struct.unpack("<IHB", data[position : position + 7])
        payload = data[position + 7 : position + 7 + length]
        position += 7 + length
        if kind == 1:
            yield payload
        elif kind == 2:
            parts = payload
        elif kind == 3:
            parts += payload
        elif kind == 4:
            yield parts + payload


def test_weights_and_biases_offline_holds_every_round(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("wandb")
    from wandb.proto import wandb_internal_pb2

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    out_dir = tmp_path / "run"
    result = api.run(overrides=[*RUN, "server.wandb=true", "algo.step_size=0.25"], out_dir=out_dir)
    (run_file,) = (out_dir / "wandb").glob("offline-run-*/run-*.wandb")
    history: dict[int, dict[str, object]] = {}
    config: dict[str, object] = {}
    names = []
    for data in wandb_records(run_file):
        record = wandb_internal_pb2.Record()
        record.ParseFromString(data)
        kind = record.WhichOneof("record_type")
        if kind == "history":
            items = {
                item.key or "/".join(item.nested_key): json.loads(item.value_json)
                for item in record.history.item
            }
            history[int(items["_step"])] = items
        elif kind == "run":
            names.append(record.run.display_name)
            config.update({u.key: json.loads(u.value_json) for u in record.run.config.update})
        elif kind == "config":
            config.update({u.key: json.loads(u.value_json) for u in record.config.update})
    assert sorted(history) == [1, 2, 3, 4]
    for record in result.records:
        logged = history[record["round"]]
        assert logged["fed/round_time_s"] == pytest.approx(record["round_time_s"])
        assert logged["agent/2/train_return"] == pytest.approx(record["agents"][2]["train_return"])
    assert "eval/mean/return" in history[2] and "eval/mean/return" not in history[1]
    assert config["algo.step_size"] == 0.25 and config["env.family"] == "gridworld"
    assert names == ["run"], "the run is named after its directory"


# --- one run-directory convention --------------------------------------------------------------

CONVENTION = re.compile(r"^runs/\d{8}-\d{6}-gridworld-fedhpg(-\d+)?$")
SMALL = [
    "agents.num_agents=2", "agents.budget.batch_size=[2]", "agents.budget.local_iters=[1]",
    "agents.speeds=[1]", "agents.step_delays_s=[0]", "rounds=1", "eval.episodes=1",
]  # fmt: skip


def test_run_directories_are_named_one_way(tmp_path: Path) -> None:
    run = compose(["env=gym", "env.id=MountainCar-v0", "algo=fedhpgvr"])
    first = new_run_dir(run, root=tmp_path, now=1_800_000_000.0)
    assert re.fullmatch(r"\d{8}-\d{6}-MountainCar-v0-fedhpgvr", first.name), first
    assert first.parent == tmp_path
    first.mkdir()
    second = new_run_dir(run, root=tmp_path, now=1_800_000_000.0)  # the same second
    assert second.name == f"{first.name}-2"


@pytest.mark.parametrize("script", ["fedhpg-run", "fedhpg-server"])
def test_every_entry_point_writes_runs_dated_env_algo(script: str, tmp_path: Path) -> None:
    if script == "fedhpg-server":  # its agents by hand: the server's directory is the point
        from procs import free_port, processes, start

        port = free_port()
        with processes() as started:
            server = start(started, script, [*SMALL, f"server.port={port}"], cwd=tmp_path)
            for k in range(2):
                start(
                    started, "fedhpg-agent", [*SMALL, f"server.port={port}", f"agent.index={k}"],
                    cwd=tmp_path,
                )  # fmt: skip
            out, err = server.communicate(timeout=120)
        returncode = server.returncode
    else:
        result = subprocess.run(
            [str(BIN / script), *SMALL], cwd=tmp_path, capture_output=True, text=True,
            timeout=120, env={**os.environ, "FEDHPG_LOG_LEVEL": "WARNING"},
        )  # fmt: skip
        out, err, returncode = result.stdout, result.stderr, result.returncode
    assert returncode == 0, err[-2000:]
    made = [p.relative_to(tmp_path).as_posix() for p in tmp_path.glob("runs/*")]
    assert len(made) == 1 and CONVENTION.match(made[0]), made
    assert (tmp_path / made[0] / "metrics.jsonl").is_file()
    assert not (tmp_path / "outputs").exists() and not (tmp_path / made[0] / ".hydra").exists()
    assert f"run directory: {(tmp_path / made[0]).resolve()}" in out


def test_a_distributed_api_run_keeps_and_returns_its_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    result = api.run(overrides=SMALL, distributed=True)
    assert result.out_dir is not None and result.out_dir.is_dir(), "it was deleted before"
    assert CONVENTION.match(result.out_dir.resolve().relative_to(tmp_path.resolve()).as_posix())
    assert (result.out_dir / "summary.json").is_file()
