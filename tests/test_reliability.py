"""Fault injection with real processes on loopback: agents killed mid-round (restarted, or
not), a slow straggler, and a registered agent that misbehaves. Every test is bounded in time
and every process it starts is killed at the end, pass or fail.

Heartbeats run fast here (0.25 s, liveness 4) so that dead peers are noticed within a second.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from peers import ScriptedAgent, hello_for
from procs import free_port, processes, start, start_federation, wait_until

from fedhpg.common.records.types import UpdateColumns, UpdateStats
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import (
    Train,
    Update,
)
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120
FAST_LIVENESS = ["server.heartbeat_interval_s=0.25", "server.heartbeat_liveness=4"]


def _records(metrics: Path) -> list[dict]:
    if not metrics.exists():
        return []
    return [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]


def _wait_for_round(metrics: Path, count: int) -> None:
    assert wait_until(lambda: len(_records(metrics)) >= count, TIMEOUT_S), (
        f"the federation never completed {count} rounds"
    )


# ~21 s: make test-long. fast cover: tests/test_launcher.py::
# test_a_killed_agent_is_restarted_and_the_run_ends_as_if_nothing_happened (a SIGKILLed agent
# rejoins, θ̃ the uninterrupted in-process one) and tests/test_hosts.py::
# test_a_killed_host_is_restarted_and_its_agents_rejoin (presumed dead, rejoined, θ̃ the same)
@pytest.mark.slow
@pytest.mark.solo  # the kill must land inside round 4 (0.2 s after round 3), 1 s liveness
def test_agent_killed_mid_round_rejoins_and_theta_is_unchanged(tmp_path: Path) -> None:
    """wait_all: kill -9 an agent in the middle of a round and start it again; it rejoins at
    the open round, redoes exactly the lost work, and the run ends with the θ of an
    uninterrupted run, every round averaged over all K agents."""
    run_keys = [
        "rounds=10", "seed=7", "agents.num_agents=3", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[2]", "agents.speeds=[1]", "agents.step_delays_s=[0.002]",
        "eval.every=5", "eval.episodes=5",
    ]  # fmt: skip
    out_dir = tmp_path / "run"
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}", *FAST_LIVENESS]
    metrics = out_dir / "metrics.jsonl"
    with processes() as started:
        server, agents = start_federation(started, [*run_keys, *wire], 3, cwd=tmp_path)
        _wait_for_round(metrics, 3)
        time.sleep(0.2)  # rounds take ~0.7 s here: this lands inside round 4
        agents[1].send_signal(signal.SIGKILL)
        agents[1].wait(timeout=10)
        restarted = start(
            started, "fedhpg-agent", [*run_keys, *wire, "agent.index=1"], cwd=tmp_path
        )
        _, server_err = server.communicate(timeout=TIMEOUT_S)
        for agent in (agents[0], agents[2], restarted):
            agent.wait(timeout=30)
    assert server.returncode == 0, server_err[-3000:]
    assert [a.returncode for a in (agents[0], agents[2], restarted)] == [0, 0, 0]
    assert "agent-1 presumed dead" in server_err
    assert "agent-1 rejoined after" in server_err and "sent it the open round" in server_err
    records = _records(metrics)
    assert [r["round"] for r in records] == list(range(1, 11))
    assert all(r["updates"] == 3 and "stragglers" not in r for r in records)
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 10
    assert torch.equal(checkpoint.theta, run_in_process(compose(run_keys)))


@pytest.mark.slow
@pytest.mark.solo  # agents 0 and 2 must make a 1.5 s round deadline every round
def test_deadline_policy_aggregates_without_the_dead_and_the_slow(tmp_path: Path) -> None:
    """deadline: agent-1 is too slow for the round deadline and agent-2 is killed mid-run and
    never comes back; every round still completes, from the updates that arrived, and the
    metrics name who is missing."""
    run_keys = [
        "rounds=8", "seed=2", "agents.num_agents=3", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]",
        # agent-1's env steps cost 50 ms: one iteration takes seconds, far past the deadline.
        "agents.step_delays_s=[0.001,0.05,0.001]",
        "eval.every=4", "eval.episodes=5",
        "server.round_policy=deadline", "server.round_deadline_s=1.5", "server.min_agents=1",
    ]  # fmt: skip
    out_dir = tmp_path / "run"
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}", *FAST_LIVENESS]
    metrics = out_dir / "metrics.jsonl"
    with processes() as started:
        server, agents = start_federation(started, [*run_keys, *wire], 3, cwd=tmp_path)
        _wait_for_round(metrics, 3)
        agents[2].send_signal(signal.SIGKILL)
        _, server_err = server.communicate(timeout=TIMEOUT_S)
        agents[0].wait(timeout=30)
        agents[1].wait(timeout=30)
    assert server.returncode == 0, server_err[-3000:]
    assert agents[0].returncode == 0 and agents[1].returncode == 0
    assert "agent-2 presumed dead" in server_err
    records = _records(metrics)
    assert [r["round"] for r in records] == list(range(1, 9))
    for record in records:
        assert "agent-1" in record["stragglers"], record["round"]
        assert record["updates"] == 3 - len(record["stragglers"])
        assert [a["id"] for a in record["agents"]] == [
            f"agent-{k}" for k in range(3) if f"agent-{k}" not in record["stragglers"]
        ]
    assert records[0]["stragglers"] == ["agent-1"], "agent-2 was alive at first"
    assert records[-1]["stragglers"] == ["agent-1", "agent-2"]
    assert records[-1]["updates"] == 1
    evaluations = [r["eval"] for r in records if "eval" in r]
    assert evaluations and all("agent-0" in e for e in evaluations)
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["agent_deaths"] >= 1


def _update(round_index: int, theta: np.ndarray, agent: int = 1) -> Update:
    stats = UpdateStats(trajectories=1, env_steps=1, compute_s=0.0, train_return=0.0)
    return Update(
        round=round_index,
        agents=[agent],
        thetas=theta.astype(np.float32)[None],
        stats=UpdateColumns.of([stats]),
    )


def test_bad_and_late_updates_of_a_registered_agent_are_never_averaged(tmp_path: Path) -> None:
    """A registered agent's update that moves θ too far is rejected and counted as its
    failure for the round; its update for a round that has closed is discarded with a log
    line; a well-formed update is averaged."""
    run_keys = [
        "rounds=5", "seed=4", "agents.num_agents=2", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0.001]",
        "eval.every=5", "eval.episodes=5", "server.round_policy=deadline",
        "server.round_deadline_s=1.0", "server.min_agents=1", "server.max_update_norm=5",
    ]  # fmt: skip
    port = free_port()
    out_dir = tmp_path / "run"
    wire = [f"server.port={port}", f"server.out_dir={out_dir}", *FAST_LIVENESS]
    hello = hello_for(compose(run_keys), 1)
    held: list[Train] = []

    def answer(train: Train) -> list[Update]:
        if train.round == 1:  # far beyond server.max_update_norm=5
            return [_update(1, train.theta + 100.0)]
        if train.round == 2:  # say nothing until round 3 has started
            held.append(train)
            return []
        late = [_update(2, held.pop().theta)] if held else []
        return [*late, _update(train.round, train.theta)]  # a zero step: well-formed

    with processes() as started:
        server = start(started, "fedhpg-server", [*run_keys, *wire], cwd=tmp_path)
        scripted = ScriptedAgent(port, hello, answer)
        scripted.thread.start()
        try:
            agent = start(
                started, "fedhpg-agent", [*run_keys, *wire, "agent.index=0"], cwd=tmp_path
            )
            _, server_err = server.communicate(timeout=TIMEOUT_S)
            agent.wait(timeout=30)
        finally:
            scripted.close()
    assert server.returncode == 0, server_err[-3000:]
    assert scripted.errors == [] and scripted.rounds_seen == [1, 2, 3, 4, 5]
    assert scripted.refusals == ["bad_update"], "only the round-1 update was refused"
    records = _records(out_dir / "metrics.jsonl")
    first, second = records[0], records[1]
    assert first["updates"] == 1 and "server.max_update_norm=5" in first["failures"]["agent-1"]
    assert [a["id"] for a in first["agents"]] == ["agent-0"]
    assert second["updates"] == 1 and second["stragglers"] == ["agent-1"]
    assert "discarded a late update from agent-1 for round 2" in server_err
    assert all(r["updates"] == 2 for r in records[2:])
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["late_answers"] == 1


def test_one_rogue_spewing_nan_cannot_end_a_buffered_run(tmp_path: Path) -> None:
    """Buffered rounds, M = 2 of K = 4: agent-3 answers every request at once with a NaN θ_k
    (it ended the run at version 1 before: the abort counted rejections in a row, not agents).
    Each of its updates is refused and counted, it waits for the next θ̃, and the honest three
    carry the run to its end with a finite θ̃."""
    run_keys = [
        "rounds=6", "seed=5", "agents.num_agents=4", "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0.001]",
        "eval.every=6", "eval.episodes=3", "server.round_policy=buffered",
        "server.buffer_size=2", "server.tensorboard=false",
    ]  # fmt: skip
    port = free_port()
    out_dir = tmp_path / "run"
    wire = [f"server.port={port}", f"server.out_dir={out_dir}", *FAST_LIVENESS]
    rogue = ScriptedAgent(
        port,
        hello_for(compose(run_keys), 3),
        lambda train: [_update(train.round, np.full_like(train.theta, np.nan), agent=3)],
    )
    with processes() as started:
        server = start(started, "fedhpg-server", [*run_keys, *wire], cwd=tmp_path)
        rogue.thread.start()
        try:
            honest = [
                start(started, "fedhpg-agent", [*run_keys, *wire, f"agent.index={k}"], cwd=tmp_path)
                for k in range(3)
            ]
            _, server_err = server.communicate(timeout=TIMEOUT_S)
            for agent in honest:
                agent.wait(timeout=30)
        finally:
            rogue.close()
    assert server.returncode == 0, server_err[-3000:]
    assert [a.returncode for a in honest] == [0, 0, 0]
    records = _records(out_dir / "metrics.jsonl")
    assert [r["round"] for r in records] == list(range(1, 7))
    assert all("agent-3" not in [a["id"] for a in r["agents"]] for r in records)
    refused = [r for r in records if "agent-3" in r.get("failures", {})]
    assert refused and all("NaN" in r["failures"]["agent-3"] for r in refused)
    # parked until the next θ̃: at most one of its updates is refused per version
    assert len(rogue.rounds_seen) <= len(records) + 1, rogue.rounds_seen
    assert rogue.refusals and set(rogue.refusals) == {"bad_update"}
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and bool(torch.isfinite(checkpoint.theta).all())
