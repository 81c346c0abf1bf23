"""Real processes for federation tests: start console scripts, always clean them up."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

BIN = Path(sys.prefix) / "bin"
QUIET = {"FEDHPG_LOG_LEVEL": "WARNING"}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux /proc)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as handle:
            return [int(p) for p in handle.read().split()]
    except FileNotFoundError:
        return []


def child_named(pid: int, name: str) -> int:
    """The direct child of ``pid`` whose /proc/PID/comm is ``name`` (fedhpg-run names each
    process it forks: "server", "agent-2"); pids wrap, so the newest child need not be the
    highest."""
    for child in child_pids(pid):
        try:
            with open(f"/proc/{child}/comm") as handle:
                if handle.read().strip() == name:
                    return child
        except FileNotFoundError:
            continue
    raise LookupError(f"no child of {pid} is named {name!r}")


@contextmanager
def sigint_ignored(ignored: bool = True) -> Iterator[None]:
    """Within the block, SIGINT is ignored (when ``ignored``), so a process started there
    inherits it ignored at exec, as a shell's background job does; put back after."""
    before = signal.getsignal(signal.SIGINT)
    if ignored:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def wait_until(predicate, timeout_s: float, interval_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return predicate()


@contextmanager
def processes() -> Iterator[list[subprocess.Popen]]:
    """Collects started processes; kills whatever is left (and its children) on exit."""
    started: list[subprocess.Popen] = []
    try:
        yield started
    finally:
        for process in started:
            if process.poll() is None:
                for child in child_pids(process.pid):
                    os.kill(child, signal.SIGKILL)
                process.kill()
            process.wait(timeout=10)


def start(
    started: list[subprocess.Popen], script: str, args: Sequence[str], *, cwd: Path
) -> subprocess.Popen:
    process = subprocess.Popen(
        [str(BIN / script), *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **QUIET},
    )
    started.append(process)
    return process


def start_federation(
    started: list[subprocess.Popen], args: Sequence[str], num_agents: int, *, cwd: Path
) -> tuple[subprocess.Popen, list[subprocess.Popen]]:
    """``fedhpg-server`` and agents 0 … K−1, all with the same overrides."""
    server = start(started, "fedhpg-server", args, cwd=cwd)
    agents = [
        start(started, "fedhpg-agent", [*args, f"agent.index={k}"], cwd=cwd)
        for k in range(num_agents)
    ]
    return server, agents
