"""TensorBoard event files beside metrics.jsonl: TensorBoard's own reader finds every round's
scalars under grouped keys with the values metrics.jsonl holds; a resumed run shows no round
twice; the sink can be turned off, and a missing tensorboard package only costs a warning."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from fedhpg.server.checkpoint import checkpoint_path
from fedhpg.server.commands import api

RUN = ["rounds=4", "seed=3", "eval.every=2", "eval.episodes=4"]


def scalars(out_dir: Path) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(out_dir / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    return {
        tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]
    }


def metrics(out_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]


def test_tensorboard_reads_each_rounds_scalars_under_grouped_keys(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=RUN, out_dir=out_dir)
    board, records = scalars(out_dir), metrics(out_dir)
    approx = pytest.approx  # event files hold float32
    assert [step for step, _ in board["fed/round_time_s"]] == [1, 2, 3, 4]
    assert [v for _, v in board["fed/round_time_s"]] == approx(
        [r["round_time_s"] for r in records], rel=1e-6
    )
    assert [v for _, v in board["fed/trajectories_per_agent"]] == approx(
        [r["trajectories_per_agent"] for r in records], rel=1e-6
    )
    for k in range(4):
        assert [v for _, v in board[f"agent/{k}/train_return"]] == approx(
            [r["agents"][k]["train_return"] for r in records], rel=1e-6, abs=1e-7
        )
        assert [v for _, v in board[f"agent/{k}/trajectories"]] == [
            r["agents"][k]["trajectories"] for r in records
        ]
        evaluated = [(r["round"], r["eval"][f"agent-{k}"]["return_mean"]) for r in records[1::2]]
        assert board[f"eval/agent-{k}/return"] == [(s, approx(v, abs=1e-7)) for s, v in evaluated]
    assert [s for s, _ in board["eval/mean/return"]] == [2, 4]
    assert all(v > 0 for _, v in board["fed/theta_step_norm"]), "θ̃ moved every round"


def test_past_tensorboard_agents_only_the_spread_over_agents_is_written(tmp_path: Path) -> None:
    """4 agents with server.tensorboard_agents=3: no agent/<k>/ or eval/<id>/ keys, and the
    agents/<field>/mean|min|max of every round equal metrics.jsonl's (also written when the
    per-agent keys are)."""
    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN, "server.tensorboard_agents=3"], out_dir=out_dir)
    board, records = scalars(out_dir), metrics(out_dir)
    assert not [t for t in board if t.startswith("agent/") or t.startswith("eval/agent-")]
    assert [s for s, _ in board["eval/mean/return"]] == [2, 4]
    for statistic, reduce in (("mean", np.mean), ("min", np.min), ("max", np.max)):
        expected = [reduce([a["train_return"] for a in r["agents"]]) for r in records]
        assert [v for _, v in board[f"agents/train_return/{statistic}"]] == pytest.approx(
            expected, rel=1e-6, abs=1e-7
        )
    assert all(v > 0 for _, v in board["agents/update_norm/min"])
    with_agents = tmp_path / "all"
    api.run(overrides=[*RUN, "rounds=1"], out_dir=with_agents)
    assert {"agents/train_return/mean", "agent/0/train_return"} <= set(scalars(with_agents))


def test_a_resumed_run_shows_no_round_twice(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN[1:], "rounds=3"], out_dir=out_dir)
    # A crash after round 3 was shown but before its checkpoint was kept: resume from round 2.
    checkpoint_path(out_dir / "checkpoints", 3).unlink()
    before = dict(scalars(out_dir)["fed/round_time_s"])
    api.run(overrides=[*RUN, "resume=true"], out_dir=out_dir)
    after = scalars(out_dir)["fed/round_time_s"]
    assert [step for step, _ in after] == [1, 2, 3, 4]
    records = metrics(out_dir)
    assert dict(after)[3] == pytest.approx(records[2]["round_time_s"], rel=1e-6)
    assert dict(after)[3] != before[3], "round 3 is the resumed run's, the old one was purged"
    assert dict(after)[1] == before[1]


def test_a_new_event_file_sorts_after_the_ones_before_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """TensorBoard reads a run's files in name order: a file opened later sorts later, whether
    the one before came from this process within the same second (its counter at 9, the new
    one's at 10) or from another process whose name sorts high (a later second on its clock)."""
    import itertools
    import time

    from fedhpg.server import metrics

    monkeypatch.setattr(metrics, "_files_opened", itertools.count(9))
    monkeypatch.setattr(time, "time", lambda: 1_700_000_000.5)
    directory = tmp_path / "tensorboard"
    opened: list[str] = []
    for _ in range(2):
        metrics.EventFile(directory).close()
        (new,) = {p.name for p in directory.iterdir()} - set(opened)
        opened.append(new)
    stranger = directory / "events.out.tfevents.1700000007.other-host.99999.0"
    stranger.write_bytes(b"")
    metrics.EventFile(directory).close()
    names = sorted(p.name for p in directory.iterdir())
    assert len(set(names)) == 4
    assert names[:2] == opened and names[2] == stranger.name
    assert names[3].split(".")[3] == "1700000008"


def test_the_sink_can_be_turned_off(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN, "rounds=1", "server.tensorboard=false"], out_dir=out_dir)
    assert (out_dir / "metrics.jsonl").exists() and not (out_dir / "tensorboard").exists()


def test_without_tensorboard_installed_a_warning_and_the_run_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # The package cannot be uninstalled for one test: a None entry makes its import fail.
    monkeypatch.setitem(sys.modules, "tensorboard.compat.proto.event_pb2", None)
    out_dir = tmp_path / "run"
    with caplog.at_level(logging.WARNING, logger="fedhpg.server.metrics"):
        result = api.run(overrides=[*RUN, "rounds=2"], out_dir=out_dir)
    assert len(result.records) == 2 and not (out_dir / "tensorboard").exists()
    warnings = [r for r in caplog.records if "tensorboard is not installed" in r.getMessage()]
    assert len(warnings) == 1


def test_the_runs_hyperparameters_are_in_the_hparams_dashboard(tmp_path: Path) -> None:
    from tensorboard.plugins.hparams import metadata, plugin_data_pb2

    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN, "rounds=2", "algo.step_size=0.25"], out_dir=out_dir)
    events = EventAccumulator(str(out_dir / "tensorboard"))
    events.Reload()
    content = events.PluginTagToContent(metadata.PLUGIN_NAME)
    experiment = plugin_data_pb2.HParamsPluginData.FromString(
        content[metadata.EXPERIMENT_TAG]
    ).experiment
    assert {"algo.step_size", "env.family", "seed", "agents.num_agents"} <= {
        h.name for h in experiment.hparam_infos
    }
    assert {m.name.tag for m in experiment.metric_infos} >= {"eval/mean/return"}
    start = plugin_data_pb2.HParamsPluginData.FromString(
        content[metadata.SESSION_START_INFO_TAG]
    ).session_start_info
    assert start.hparams["algo.step_size"].number_value == 0.25
    assert start.hparams["env.family"].string_value == "gridworld"


def test_the_records_are_framed_as_tensorboards_own_writer_frames_them(tmp_path: Path) -> None:
    """Every record is the bytes tensorboard's RecordWriter writes for it (the CRCs compiled
    instead of its pure-Python ones), and its reader takes every one back."""
    import io

    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.summary.writer.record_writer import RecordWriter

    from fedhpg.server import metrics

    for data in (b"", b"x", bytes(range(256)) * 130):
        theirs = io.BytesIO()
        RecordWriter(theirs).write(data)
        assert metrics.tf_record(data) == theirs.getvalue()
    out_dir = tmp_path / "run"
    api.run(overrides=[*RUN, "rounds=2"], out_dir=out_dir)
    (path,) = (out_dir / "tensorboard").glob("events.out.tfevents.*")
    read = list(EventFileLoader(str(path)).Load())
    assert [e.step for e in read if e.summary.value] == [0, 0, 1, 2]
    assert isinstance(read[0], Event) and read[0].file_version == "brain.Event:2"


def test_update_norms_are_each_agents_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """‖θ_k − θ̃‖ per agent, taken a slab of rows at a time (2 here) over the result's rows:
    each agent's norm is its own row's."""

    from fedhpg.common.records.types import RoundResult, UpdateColumns, UpdateStats
    from fedhpg.server import metrics

    monkeypatch.setattr(metrics, "NORM_ROWS", 2)
    rng = np.random.default_rng(0)
    before = rng.standard_normal(7)
    stats = UpdateStats(trajectories=1, env_steps=1, compute_s=0.0, train_return=0.0)
    thetas = {k: rng.standard_normal(7).astype(np.float32) for k in (0, 2, 4, 7, 9)}
    updates = RoundResult(
        round=1,
        agents=list(thetas),
        thetas=np.stack(list(thetas.values())),
        stats=UpdateColumns.of([stats] * len(thetas)),
    )
    norms = metrics._update_norms(updates, before)
    assert norms == {
        k: pytest.approx(float(np.linalg.norm(t.astype(np.float64) - before)), rel=1e-12)
        for k, t in thetas.items()
    }
    assert metrics._update_norms(RoundResult.empty(1, 7), before) == {}
