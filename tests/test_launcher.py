"""fedhpg-run supervises its processes: a crashed agent is restarted and rejoins (up to
``agent.max_restarts``), one crash too many stops the federation with a non-zero status,
Ctrl-C stops it too, and no process is left behind either way."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
import torch
from procs import alive, child_named, child_pids, processes, sigint_ignored, start, wait_until

from fedhpg.common.runtime.cli import EXIT_RUN_ABORTED, compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import launcher

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
        os.kill(child_named(launcher.pid, "agent-2"), signal.SIGKILL)
        out, err = launcher.communicate(timeout=30)
        stderr = err + out
    assert launcher.returncode == 1
    assert "exited with status -9" in stderr
    assert wait_until(lambda: not any(alive(pid) for pid in children), 10)


@pytest.mark.parametrize(
    ("stop", "inherited", "status"),
    [
        (signal.SIGINT, "default", 130),
        (signal.SIGINT, "ignored", 130),
        (signal.SIGTERM, "default", 143),  # 128 + 15, as a shell reports it (130 before)
    ],
    ids=["ctrl-c", "ctrl-c-ignored", "sigterm"],
)
def test_a_stopped_run_leaves_no_process_and_says_how_to_continue(
    tmp_path: Path, stop: int, inherited: str, status: int
) -> None:
    """'ignored': the launcher starts with SIGINT ignored, as a shell's background job does
    (and as a test process may pass on), and must still stop on it."""
    with processes() as started:
        with sigint_ignored(inherited == "ignored"):  # inherited by the launcher at exec
            launcher, children = _running_federation(started, tmp_path)
        saved = tmp_path / "run" / "checkpoints"
        # a valid checkpoint, not the temporary file one is written to first
        assert wait_until(lambda: saved.is_dir() and latest_valid_checkpoint(saved) is not None, 60)
        launcher.send_signal(stop)
        # communicate, not wait: the federation's processes share the launcher's pipes, and a
        # pipe nobody drains blocks the process writing to it once it is full (64 KiB)
        _, stderr = launcher.communicate(timeout=60)
    assert launcher.returncode == status
    assert wait_until(lambda: not any(alive(pid) for pid in children), 10)
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("interrupted after round "), stderr[-2000:]
    assert f"run directory: {tmp_path / 'run'}" in last
    assert last.endswith(f"continue it with: fedhpg-run resume={tmp_path / 'run'}")


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
        os.kill(child_named(launcher.pid, "agent-2"), signal.SIGKILL)
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
    # said once, by the server: its forked agents leave the abort to it
    assert stderr.count("every agent's update was rejected") == 1, stderr[-2000:]
    assert "restarting it" not in stderr, stderr[-2000:]
    assert "Traceback" not in stderr + stdout


def test_a_stopped_server_says_how_to_continue(tmp_path: Path) -> None:
    from procs import free_port

    one = [k if not k.startswith("agents.num_agents=") else "agents.num_agents=1" for k in LONG_RUN]
    keys = [*one, f"server.port={free_port()}", "server.out_dir=run"]
    with processes() as started:
        server = start(started, "fedhpg-server", keys, cwd=tmp_path)
        agent = start(started, "fedhpg-agent", [*keys, "agent.index=0"], cwd=tmp_path)
        saved = tmp_path / "run" / "checkpoints"
        # a valid checkpoint, not the temporary file one is written to first
        assert wait_until(lambda: saved.is_dir() and latest_valid_checkpoint(saved) is not None, 60)
        server.send_signal(signal.SIGTERM)
        _, stderr = server.communicate(timeout=60)
        agent.communicate(timeout=60)
    assert server.returncode == 143, stderr[-2000:]
    lines = stderr.strip().splitlines()
    assert lines[-1] == "interrupted"
    assert lines[-2].endswith("continue it with: fedhpg-server resume=true server.out_dir=run")
    assert agent.returncode == 3, "the agent is told the run was stopped"


def test_the_kernels_are_compiled_before_the_server_starts_its_clock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server's clock for registrations starts when it listens: numba's compilation (tens
    of seconds on a cold cache) happens before the server is forked, not while it waits."""
    from fedhpg.server.commands import launcher

    events: list[str] = []

    class Forked(Exception):
        pass

    def start(self, target, args, name):
        events.append(f"start {name}")
        raise Forked

    monkeypatch.setattr(launcher, "prepare_compiled_engine", lambda run: events.append("compile"))
    monkeypatch.setattr(launcher.Supervisor, "start", start)
    run = compose(["env=cartpole", f"server.out_dir={tmp_path / 'run'}"])
    with pytest.raises(Forked):
        launcher._launch(run, tmp_path / "run", launcher.Supervisor())
    assert events == ["compile", "start server"]


@pytest.mark.parametrize("existed", [False, True], ids=["made-by-hydra", "named-existing"])
def test_a_failed_start_removes_the_run_directory_hydra_made_for_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, existed: bool
) -> None:
    """Hydra makes the job's directory before the job starts: a run that fails before it
    writes anything there takes it away, unless it was there before the command."""
    import sys

    from fedhpg.server.commands import launcher

    out_dir = tmp_path / "run"
    if existed:
        out_dir.mkdir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["fedhpg-run", "rounds=1", f"server.out_dir={out_dir}"])
    monkeypatch.setattr(launcher, "run_federation", lambda run, port: 1)
    with pytest.raises(SystemExit) as exit_:
        launcher.main()
    assert exit_.value.code == 1
    assert out_dir.exists() == existed


def _exit_after(seconds: float, status: int) -> None:
    import sys
    import time

    time.sleep(seconds)
    sys.exit(status)


@pytest.mark.parametrize(
    ("agent_s", "agent_status", "launch_status"),
    [(60.0, 0, 0), (0.5, 1, 1)],
    ids=["lingering-is-stopped", "failed-counts"],
)
def test_after_a_completed_run_the_agents_get_a_grace_then_are_stopped(
    monkeypatch: pytest.MonkeyPatch, agent_s: float, agent_status: int, launch_status: int
) -> None:
    """The server ended the run well: an agent process still running after FINISH_GRACE_S
    (a host that missed the shutdown while reconnecting) is stopped with a warning, and the
    launch succeeds; one that ended with an error fails it."""
    from fedhpg.server.commands import launcher

    monkeypatch.setattr(launcher, "FINISH_GRACE_S", 1.0)
    supervisor = launcher.Supervisor()
    agent = supervisor.start(_exit_after, (agent_s, agent_status), "host-0-1")
    server = supervisor.start(_exit_after, (0.1, 0), "server")
    try:
        assert supervisor.wait(server) == launch_status
        assert not agent.is_alive()
    finally:
        supervisor.stop_all()


class _Ending:
    """A child process as the supervisor reads it: running for its first ``running`` reads
    of the exit status, ended with ``code`` from then on (a process that ends while the
    supervisor looks at it)."""

    def __init__(self, name: str, code: int, running: int) -> None:
        self.name, self.code, self.running, self.reads = name, code, running, 0
        self.sentinel = -1

    @property
    def exitcode(self) -> int | None:
        self.reads += 1
        return None if self.reads <= self.running else self.code

    def is_alive(self) -> bool:
        return self.exitcode is None

    def join(self, timeout: float | None = None) -> None:
        pass

    def terminate(self) -> None:
        pass

    def kill(self) -> None:
        pass


def test_an_agent_that_ends_as_the_run_is_aborted_is_not_restarted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The agent exits with the aborted-run status just after the supervisor first reads
    its status: the supervisor acts on one reading per process and pass, so it neither
    restarts the agent nor blames it; the server's own status ends the federation."""
    supervisor = launcher.Supervisor(max_restarts=2)
    agent = _Ending("agent-0", EXIT_RUN_ABORTED, running=1)
    server = _Ending("server", 1, running=2)
    supervisor.children = [agent, server]  # type: ignore[list-item]
    started: list[str] = []
    monkeypatch.setattr(supervisor, "start", lambda target, args, name: started.append(name))
    monkeypatch.setattr(launcher, "wait", lambda sentinels, timeout: None)
    assert supervisor.wait(server) == 1  # type: ignore[arg-type]
    assert started == [], "the agent of an aborted run was restarted"
