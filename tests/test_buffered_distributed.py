"""Buffered asynchronous rounds with real agent processes (server/buffered_zmq.py).

fedhpg-run on loopback TCP: a server and one process per agent, devices emulated by sleeping
(the demo's speeds 1/1/0.5/0.25), run directories and checkpoints on disk; nothing is mocked.
"""

from __future__ import annotations

import json
import os
import signal
from collections import Counter
from pathlib import Path
from typing import Any

import torch
from procs import child_named, free_port, processes, start, wait_until

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120
QUIET = ["server.tensorboard=false"]


def _run(tmp_path: Path, overrides: list[str]) -> tuple[Path, str]:
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*overrides, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        stdout, stderr = launcher.communicate(timeout=TIMEOUT_S)
    assert launcher.returncode == 0, (stdout + stderr)[-3000:]
    return out_dir, stdout + stderr


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _records(out_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]


def test_buffered_processes_follow_arrival_order(tmp_path: Path) -> None:
    """M = 2 of K = 4, agent-3 sleeping to 1/4 speed with the largest budget (B=20, τ=3
    against agent-0's B=8, τ=2: ~15× agent-0's time per update): every version aggregates
    M updates, and each fast agent is aggregated more often than agent-3."""
    overrides = [*QUIET, "rounds=12", "seed=3", "server.round_policy=buffered"]
    out_dir, _ = _run(tmp_path, [*overrides, "server.buffer_size=2", "eval.every=4"])
    records = _records(out_dir)
    assert [r["round"] for r in records] == list(range(1, 13))
    for record in records:
        ids = [a["id"] for a in record["agents"]]
        assert record["updates"] == 2 and len(set(ids)) == 2, record
        assert len(record["staleness"]) == 2 and min(record["staleness"]) >= 0
    clocks = [r["emulated_clock_s"] for r in records]
    assert clocks == sorted(clocks), "the emulated clock never goes back"
    counts = Counter(a["id"] for r in records for a in r["agents"])
    assert min(counts["agent-0"], counts["agent-1"]) > counts["agent-3"], counts
    # evaluation pauses dispatch: every agent evaluates, every eval.every versions
    assert [r["round"] for r in records if "eval" in r] == [4, 8, 12]
    everyone = [f"agent-{k}" for k in range(4)]
    assert all(sorted(r["eval"]) == everyone for r in records if "eval" in r)
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 12


def test_buffered_with_m_equal_k_is_wait_all_bit_for_bit(tmp_path: Path) -> None:
    """M = K: each buffer holds the K fresh updates from one θ̃, each agent's n-th update uses
    round n's streams, so the processes end with the in-process wait_all θ̃ exactly."""
    keys = [
        *QUIET,
        "rounds=4",
        "seed=7",
        "agents.num_agents=3",
        "agents.budget.batch_size=[6,8,10]",
        "agents.budget.local_iters=[1,2,3]",
        "agents.speeds=[1.0,1.0,0.25]",
        "agents.step_delays_s=[0]",
        "eval.every=2",
        "eval.episodes=2",
    ]
    out_dir, _ = _run(tmp_path, [*keys, "server.round_policy=buffered"])
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 4
    assert torch.equal(checkpoint.theta, run_in_process(compose(keys)))
    assert all(r["staleness"] == [0, 0, 0] for r in _records(out_dir))


def test_a_killed_agent_is_restarted_rejoins_and_the_run_ends(tmp_path: Path) -> None:
    """K = 3, M = 2, equal speeds: agent-2 is killed (SIGKILL) after the third version; the
    other two go on aggregating without it, fedhpg-run restarts it, it registers again (its
    open request re-sent with the newest θ̃) and is aggregated again before the run ends."""
    keys = [
        *QUIET,
        "rounds=24",
        "seed=3",
        "agents.num_agents=3",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0.002]",
        "eval.every=24",
        "eval.episodes=2",
        "server.heartbeat_interval_s=0.25",
        "server.heartbeat_liveness=4",
        "server.round_policy=buffered",
        "server.buffer_size=2",
    ]
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*keys, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        metrics = out_dir / "metrics.jsonl"
        assert wait_until(lambda: metrics.exists() and len(_lines(metrics)) >= 3, 60)
        killed_after = len(_lines(metrics))
        os.kill(child_named(launcher.pid, "agent-2"), signal.SIGKILL)
        stdout, stderr = launcher.communicate(timeout=TIMEOUT_S)
    logs = stdout + stderr
    assert launcher.returncode == 0, logs[-3000:]
    assert "agent-2 presumed dead" in logs and "agent-2 rejoined" in logs
    records = _records(out_dir)
    assert [r["round"] for r in records] == list(range(1, 25))
    assert all(r["updates"] == 2 for r in records)
    assert killed_after < 20, "killed mid-run"
    with_2 = [r["round"] for r in records if "agent-2" in {a["id"] for a in r["agents"]}]
    # the version open at the kill may hold an update agent-2 sent just before it
    assert [v for v in with_2 if v > killed_after + 1], f"agent-2 never came back: {with_2}"


def test_a_resumed_run_restarts_every_agent_from_the_checkpoint(tmp_path: Path) -> None:
    """Two versions, then a resume to four: the checkpoint holds each agent's count of rounds
    done, so each agent's third update uses round 3's streams; with M = K that is the
    uninterrupted in-process wait_all run exactly."""
    keys = [
        *QUIET,
        "seed=5",
        "agents.num_agents=2",
        "agents.budget.batch_size=[6,8]",
        "agents.budget.local_iters=[1,2]",
        "agents.speeds=[1.0]",
        "agents.step_delays_s=[0]",
        "eval.every=10",
        "eval.episodes=2",
    ]
    buffered = [*keys, "server.round_policy=buffered"]
    out_dir, _ = _run(tmp_path, [*buffered, "rounds=2"])
    _run(tmp_path, [*buffered, "rounds=4", "resume=true"])
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 4
    assert [r["round"] for r in _records(out_dir)] == [1, 2, 3, 4]
    assert torch.equal(checkpoint.theta, run_in_process(compose([*keys, "rounds=4"])))


def test_an_agent_host_is_refused_by_a_buffered_server(tmp_path: Path) -> None:
    """By hand (``fedhpg-server`` and ``fedhpg-agent agent.count=2``, which fedhpg-run would
    have refused up front): the host is refused at registration and exits naming why."""
    keys = [
        *QUIET,
        "rounds=2",
        "agents.num_agents=2",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
        "server.round_policy=buffered",
        "server.register_timeout_s=30",
    ]
    wire = [f"server.port={free_port()}", f"server.out_dir={tmp_path / 'run'}"]
    with processes() as started:
        start(started, "fedhpg-server", [*keys, *wire], cwd=tmp_path)
        host = start(
            started, "fedhpg-agent", [*keys, *wire, "agent.first=0", "agent.count=2"], cwd=tmp_path
        )
        _, stderr = host.communicate(timeout=TIMEOUT_S)
    assert host.returncode != 0
    assert "server refused registration (unsupported): server.round_policy=buffered" in stderr
