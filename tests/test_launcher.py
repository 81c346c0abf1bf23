"""fedhpg-run supervises its processes: a crashed agent is restarted and rejoins (up to
``agent.max_restarts``), one crash too many stops the federation with a non-zero status,
Ctrl-C stops it too, and no process is left behind either way."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
import torch
from procs import alive, child_pids, processes, start, wait_until

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

LONG_RUN = [
    "rounds=1000",
    "agents.num_agents=3",
    "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]",
    "agents.speeds=[1]",
    "agents.step_delays_s=[0.002]",
]


def _running_federation(started: list, tmp_path: Path, *extra: str):
    launcher = start(
        started,
        "fedhpg-run",
        [
            *LONG_RUN,
            *extra,
            f"server.out_dir={tmp_path / 'run'}",
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        cwd=tmp_path,
    )
    metrics = tmp_path / "run" / "metrics.jsonl"
    assert wait_until(lambda: metrics.exists() and metrics.read_text().strip(), 60)
    children = child_pids(launcher.pid)
    assert len(children) == 4, children  # the server and three agents
    return launcher, children


def test_a_crashed_agent_without_restarts_left_stops_the_federation(tmp_path: Path) -> None:
    with processes() as started:
        launcher, children = _running_federation(started, tmp_path, "agent.max_restarts=0")
        os.kill(max(children), signal.SIGKILL)  # the last agent forked
        out, err = launcher.communicate(timeout=30)
        stderr = err + out
    assert launcher.returncode == 1
    assert "exited with status -9" in stderr
    assert wait_until(lambda: not any(alive(pid) for pid in children), 10)


@pytest.mark.parametrize("inherited", ["default", "ignored"])
def test_ctrl_c_leaves_no_process_behind(tmp_path: Path, inherited: str) -> None:
    """'ignored': the launcher starts with SIGINT ignored, as a shell's background job does
    (and as a test process may pass on), and must still stop on it."""
    before = signal.getsignal(signal.SIGINT)
    if inherited == "ignored":
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited by the launcher at exec
    with processes() as started:
        try:
            launcher, children = _running_federation(started, tmp_path)
        finally:
            signal.signal(signal.SIGINT, before)
        launcher.send_signal(signal.SIGINT)
        # communicate, not wait: the federation's processes share the launcher's pipes, and a
        # pipe nobody drains blocks the process writing to it once it is full (64 KiB)
        launcher.communicate(timeout=60)
    assert launcher.returncode == 130
    assert wait_until(lambda: not any(alive(pid) for pid in children), 10)


def test_children_die_with_a_killed_launcher(tmp_path: Path) -> None:
    with processes() as started:
        launcher, children = _running_federation(started, tmp_path)
        launcher.kill()
        launcher.communicate(timeout=30)
    assert wait_until(lambda: not any(alive(pid) for pid in children), 10)


def test_a_killed_agent_is_restarted_and_the_run_ends_as_if_nothing_happened(
    tmp_path: Path,
) -> None:
    keys = [
        "rounds=12", "seed=3", "agents.num_agents=3", "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0.004]",
        "eval.every=6", "eval.episodes=5",
        "server.heartbeat_interval_s=0.25", "server.heartbeat_liveness=4",
    ]  # fmt: skip
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*keys, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        metrics = out_dir / "metrics.jsonl"
        assert wait_until(lambda: metrics.exists() and len(metrics.read_text().split()) >= 3, 60)
        os.kill(max(child_pids(launcher.pid)), signal.SIGKILL)  # the last agent forked
        stdout, stderr = launcher.communicate(timeout=120)
    logs = stdout + stderr  # Hydra's job logging writes to stdout
    assert launcher.returncode == 0, logs[-3000:]
    assert "exited with status -9; restarting it (1 of 2 restarts" in logs
    assert "agent-2 rejoined" in logs
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 12
    assert torch.equal(checkpoint.theta, run_in_process(compose(keys)))


def test_agents_of_a_run_the_server_aborts_are_not_restarted(tmp_path: Path) -> None:
    """Every update diverges in round 1 (a step of 1e300 is inf in float32, so every
    coordinate of every θ_k is inf or NaN whatever its gradient): the server stops the run and
    tells its agents, which exit 3; restarting them would mend nothing."""
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [
                *LONG_RUN[1:],
                "env.family=cartpole",
                "rounds=3",
                "algo.step_size=1e300",
                "agent.max_restarts=2",
                f"server.out_dir={tmp_path / 'run'}",
            ],
            cwd=tmp_path,
        )
        stdout, stderr = launcher.communicate(timeout=120)
    assert launcher.returncode == 1, stderr[-2000:]
    assert "every agent's update was rejected" in stderr and "lower algo.step_size" in stderr
    assert "the run was aborted" in stderr
    assert "restarting it" not in stderr, stderr[-2000:]
    assert "Traceback" not in stderr + stdout
