"""The units ``fedhpg-cluster`` places, and what runs inside each job.

A unit is one process command line: the server's (``fedhpg-server …``) and one per agent-side
process (``agent_commands``: today ``fedhpg-agent agent.index=k …``, one unit per agent). The
job that runs a unit (:func:`run_unit`) waits, for an agent, until the server job has written
its endpoint file, adds the server's host and port to the command line, and runs the command
as a child that dies with the job. The wire stays ZeroMQ: jobs only start processes.

This module imports no torch (and submitit only inside a job): a job pays for the imports of
its command alone.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.placement import agents_per_host, host_ranges
from fedhpg.common.runtime.cli import LOG_DATE_FORMAT, LOG_FORMAT, setup_logging

logger = logging.getLogger(__name__)

ENDPOINT_NAME = "endpoint.json"
"""The server job's endpoint file, in the run directory."""
STOP_NAME = "stop"
"""Written by fedhpg-cluster into its submitit folder: every job of the run stops its command."""
STATUS_DIR = "status"
"""Beside the stop file: one ``<job id>.json`` per job, its command's exit status."""
POLL_S = 0.1
PLACED_KEYS = ("server.out_dir", "server.port", "server.host", "server.bind_all")
"""Keys the placement sets on each command line itself (the user's values are read from the
composed run instead)."""
STOP_GRACE_S = 0.8
"""A cancelled job's command gets this long after SIGTERM (submitit's local executor sends
SIGKILL to the job 1 s after its SIGINT)."""
EXIT_NO_SERVER = 4
"""An agent job whose server never wrote its endpoint file."""
PR_SET_PDEATHSIG = 1


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def passed_overrides(overrides: Sequence[str]) -> list[str]:
    """The user's overrides that every unit gets: all but ``cluster`` (the driver's alone) and
    the endpoint keys the placement sets."""
    return [
        o for o in overrides if _key(o).split(".")[0] != "cluster" and _key(o) not in PLACED_KEYS
    ]


def server_command(
    run: RunConfig, overrides: Sequence[str], run_dir: Path, *, bind_all: bool
) -> list[str]:
    """The server unit: the run directory, the endpoint file, a free port unless one is named."""
    port = run.server.port if any(_key(o) == "server.port" for o in overrides) else 0
    command = [
        "fedhpg-server",
        *passed_overrides(overrides),
        f"server.out_dir={run_dir}",
        f"server.endpoint_file={run_dir / ENDPOINT_NAME}",
        f"server.host={run.server.host}",
        f"server.port={port}",
        f"server.bind_all={str(bind_all).lower()}",
    ]
    if bind_all and run.cluster.advertise_host is not None:
        command.append(f"cluster.advertise_host={run.cluster.advertise_host}")
    return command


def agent_commands(run: RunConfig, overrides: Sequence[str]) -> list[list[str]]:
    """One command line per agent-side process; the server's host and port are added in the
    job, once known. The one place that decides how agents are grouped into processes."""
    shared = passed_overrides(overrides)
    per_host = agents_per_host(run)
    if per_host == 1:
        return [["fedhpg-agent", *shared, f"agent.index={k}"] for k in range(run.agents.num_agents)]
    # agent hosts, as fedhpg-run starts them: one job of the array per range
    return [
        ["fedhpg-agent", *shared, f"agent.first={first}", f"agent.count={count}"]
        for first, count in host_ranges(run.agents.num_agents, per_host)
    ]


def describe(command: Sequence[str]) -> str:
    """A unit in a log line: the program and what tells it from its siblings."""
    own = [a for a in command[1:] if _key(a).startswith("agent.")]
    return " ".join([command[0], *own])


# --- inside the job ---------------------------------------------------------------------------


def read_endpoint(path: Path, timeout_s: float, stop: Path) -> dict[str, object] | None:
    """The server's endpoint record once the file exists (polled); None after ``timeout_s``
    or once ``stop`` exists."""
    deadline = time.monotonic() + timeout_s
    while True:
        with contextlib.suppress(FileNotFoundError, json.JSONDecodeError):
            record = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(record, dict):
                return record
        if time.monotonic() >= deadline or stop.exists():
            return None
        time.sleep(POLL_S)


def _executable(program: str) -> str:
    """The console script beside this interpreter (the job's virtualenv), else on PATH."""
    beside = Path(sys.executable).parent / program
    return str(beside) if beside.exists() else (shutil.which(program) or program)


def _die_with_job() -> None:
    # If the job's process is killed (submitit's local cancel ends in SIGKILL), the command
    # must not outlive it: the kernel sends it SIGTERM.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def run_unit(
    command: list[str],
    endpoint_file: str | None,
    timeout_s: float,
    stop_file: str,
    *,
    job_id: str | None = None,
    log_file: str | None = None,
    cwd: str | None = None,
    env: dict[str, str] | None = None,
) -> int:
    """Run one unit in this job and return its exit status (the job's result).

    ``endpoint_file``: wait for the server's endpoint (at most ``timeout_s``) and connect there.
    ``stop_file``: when it appears, stop the command (SIGTERM): how ``fedhpg-cluster`` ends
    its jobs on any engine before it falls back to cancelling them. Arguments are plain
    strings, so that what an engine stores for the job is only that.

    A submitit job passes nothing else: its id is submitit's, its output is the job's log.
    A Ray task, whose worker process serves other tasks too, names the job (``job_id``), and
    gets the command's output and its own lines in ``log_file``, the driver's working
    directory (``cwd``) and the variables the driver passes on (``env``)."""
    level = (env or {}).get("FEDHPG_LOG_LEVEL") or os.environ.get("FEDHPG_LOG_LEVEL", "INFO")
    with _unit_log(log_file, level) as output:
        stop = Path(stop_file)
        status_dir = stop.parent / STATUS_DIR
        argv = list(command)
        if endpoint_file is not None:
            record = read_endpoint(Path(endpoint_file), timeout_s, stop)
            if record is None:
                logger.error(
                    "no server endpoint in %s (waited up to %.0f s)", endpoint_file, timeout_s
                )
                return _record_status(status_dir, job_id, EXIT_NO_SERVER)
            if record.get("transport") == "tcp":
                argv += [f"server.host={record['host']}", f"server.port={record['port']}"]
        logger.info("running %s (on %s)", " ".join(argv), socket.gethostname())
        process = subprocess.Popen(
            [_executable(argv[0]), *argv[1:]],
            preexec_fn=_die_with_job,
            cwd=cwd,
            env=None if env is None else {**os.environ, **env},
            stdout=output,
            stderr=output,
        )
        try:
            while process.poll() is None and not stop.exists():
                time.sleep(POLL_S)
            if process.poll() is None:
                logger.info("stop requested (%s): stopping %s", stop, argv[0])
        finally:  # stopped, or cancelled (SIGINT from submitit's local executor; Ray's cancel)
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    process.kill()
        return _record_status(status_dir, job_id, process.wait())


@contextlib.contextmanager
def _unit_log(log_file: str | None, level: str) -> Iterator[IO[bytes] | None]:
    """Where the unit's lines and its command's output go: the job's own stderr (None), or
    ``log_file``, opened for appending, with this module's lines there too."""
    if log_file is None:
        setup_logging(level)
        yield None
        return
    path = Path(log_file)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("ab", buffering=0) as output:
        handler = logging.FileHandler(path, encoding="utf-8")  # appends, as the command does
        handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt=LOG_DATE_FORMAT))
        logger.addHandler(handler)
        before = logger.level
        logger.setLevel(level)
        try:
            yield output
        finally:
            logger.removeHandler(handler)
            handler.close()
            logger.setLevel(before)


def _record_status(folder: Path, job_id: str | None, status: int) -> int:
    """The command's exit status as JSON beside the job's files: fedhpg-cluster reads this,
    never submitit's result pickle."""
    if job_id is None:
        import submitit

        job_id = str(submitit.JobEnvironment().job_id)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{job_id}.json"
    path.write_text(json.dumps({"status": status}), encoding="utf-8")
    return status
