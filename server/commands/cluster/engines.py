"""The cluster engines ``fedhpg-cluster`` places a federation on, behind one small interface.

An engine submits the server's unit as one job and the agent-side units as one array (or one
job, to restart a crashed unit); a job says whether it ended, with which exit status of its
command, and can be cancelled. Everything else (the order of submissions, restarts, stopping)
is the placement's own (:mod:`.main`), the same on every engine. Every engine runs
:func:`~fedhpg.server.commands.cluster.units.run_unit` in its jobs.

Here: submitit's executors, SLURM (``cluster=slurm``) and processes on this machine
(``cluster=local``). Ray's tasks are in :mod:`.ray_engine`, imported only for ``cluster=ray``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from fedhpg.common.configuration.config import RunConfig
from fedhpg.server.commands.cluster.units import STATUS_DIR, run_unit

STATE_POLL_S = 5.0
"""How often the states of a run's SLURM jobs are asked for (one ``sacct`` for all of them):
how soon a job killed before its command could report is noticed. submitit alone would ask
ever less often, up to every 10 minutes in a long run."""
SETTLE_POLL_S = 0.5


class Job(Protocol):
    """One submitted unit."""

    @property
    def job_id(self) -> str: ...

    @property
    def log(self) -> str:
        """Where its output is (a path on the shared filesystem)."""
        ...

    def done(self) -> bool: ...

    def status(self) -> tuple[int | None, str]:
        """An ended job's command's exit status; None, and why, if the job ended before its
        command did (killed, cancelled, timed out)."""
        ...

    def cancel(self) -> None:
        """Ask the engine to end the job now (it may take a while to be gone)."""
        ...


class Engine(Protocol):
    """Where a federation's units run."""

    @property
    def kind(self) -> str:
        """'slurm', 'local' or 'ray'."""
        ...

    @property
    def bind_all(self) -> bool:
        """Whether the server must listen on every interface (agents on other nodes)."""
        ...

    def check_room(self, agent_units: int) -> None:
        """Raise :class:`SubmitError` where the engine could never run the server and
        ``agent_units`` agent jobs at once (the server waits for every agent)."""
        ...

    def submit_server(self, command: list[str]) -> Job: ...

    def submit_agents(self, commands: Sequence[list[str]]) -> list[Job]:
        """The agent-side units, one array."""
        ...

    def submit_agent(self, command: list[str]) -> Job:
        """One agent-side unit again (a restart)."""
        ...

    def refresh(self, *, force: bool = False) -> None:
        """Ask the engine for its jobs' states, at most every ``STATE_POLL_S`` unless forced."""
        ...

    def close(self) -> None: ...


class SubmitError(Exception):
    """The engine refused a job (sbatch failed, say): one line, exit 1."""


@dataclass(frozen=True)
class UnitFiles:
    """What every job of a run is told: the endpoint file agents wait for, the stop file that
    ends every job's command, how long agents wait for the endpoint."""

    endpoint: Path
    stop: Path
    endpoint_timeout_s: float

    @property
    def status_dir(self) -> Path:
        return self.stop.parent / STATUS_DIR


@dataclass
class SubmititJob:
    """A submitit job; its command's exit status is the JSON its job wrote (never submitit's
    result pickle)."""

    job: Any
    files: UnitFiles

    @property
    def job_id(self) -> str:
        return str(self.job.job_id)

    @property
    def log(self) -> str:
        return str(self.job.paths.stderr)

    def done(self) -> bool:
        return bool(self.job.done())

    def status(self) -> tuple[int | None, str]:
        path = self.files.status_dir / f"{self.job_id}.json"
        try:
            return int(json.loads(path.read_text(encoding="utf-8"))["status"]), ""
        except (OSError, ValueError, KeyError, TypeError):
            return None, f"it ended before its command did (job state {self.job.state})"

    def cancel(self) -> None:
        self.job.cancel(check=False)


class SubmititEngine:
    """SLURM or local processes through submitit: the agents are one ``sbatch --array``."""

    def __init__(self, run: RunConfig, run_dir: Path, files: UnitFiles) -> None:
        import submitit

        cluster = run.cluster
        self.files = files
        self.executor = submitit.AutoExecutor(
            folder=run_dir / cluster.folder / "%j",
            cluster=None if cluster.kind == "auto" else cluster.kind,
        )
        self.executor.update_parameters(
            timeout_min=cluster.time_min,
            mem_gb=cluster.mem_gb,
            cpus_per_task=cluster.cpus_per_task,
            slurm_partition=cluster.partition,
        )
        self.gpus_per_host = cluster.gpus_per_host
        self.array_parallelism = cluster.array_parallelism
        self._asked = float("-inf")

    @property
    def kind(self) -> str:
        return str(self.executor.cluster)

    @property
    def bind_all(self) -> bool:
        return self.kind != "local"  # agents on other nodes; loopback when all are here

    def check_room(self, agent_units: int) -> None:
        return None  # sbatch refuses what the cluster could never run (one line, exit 1)

    def _submit(self, command: list[str], endpoint: Path | None) -> Any:
        timeout_s = self.files.endpoint_timeout_s if endpoint is not None else 0.0
        where = None if endpoint is None else str(endpoint)
        return self.executor.submit(run_unit, command, where, timeout_s, str(self.files.stop))

    def _as_agents(self, jobs: int) -> None:
        parameters: dict[str, Any] = {
            "name": "fedhpg-agent",
            "slurm_array_parallelism": self.array_parallelism or jobs,
        }
        if self.kind == "slurm" and self.gpus_per_host:
            parameters["slurm_gres"] = f"gpu:{self.gpus_per_host}"
        self.executor.update_parameters(**parameters)

    def submit_server(self, command: list[str]) -> Job:
        self.executor.update_parameters(name="fedhpg-server")
        try:
            return SubmititJob(self._submit(command, None), self.files)
        except Exception as error:  # the engine's own error (sbatch's message), whatever its type
            raise SubmitError(f"cannot submit the server job: {one_line(error)}") from None

    def submit_agents(self, commands: Sequence[list[str]]) -> list[Job]:
        self._as_agents(len(commands))
        try:
            with self.executor.batch():
                pending = [self._submit(c, self.files.endpoint) for c in commands]
        except Exception as error:
            raise SubmitError(f"cannot submit the agent jobs: {one_line(error)}") from None
        return [SubmititJob(job, self.files) for job in pending]

    def submit_agent(self, command: list[str]) -> Job:
        self._as_agents(1)
        try:
            return SubmititJob(self._submit(command, self.files.endpoint), self.files)
        except Exception as error:
            raise SubmitError(f"cannot resubmit an agent job: {one_line(error)}") from None

    def refresh(self, *, force: bool = False) -> None:
        if self.kind != "slurm":
            return  # a local job's state is its process's, read by done() itself
        now = time.monotonic()
        if force or now - self._asked >= STATE_POLL_S:
            import submitit

            submitit.SlurmJob.watcher.update()  # one sacct for every job of the run
            self._asked = now

    def close(self) -> None:
        return None


def settle(engine: Engine, jobs: Sequence[Job], timeout_s: float) -> list[Job]:
    """Wait (at most ``timeout_s``) until the engine reports every job ended; those it does
    not."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = [job for job in jobs if not job.done()]
        if not left or time.monotonic() >= deadline:
            return left
        time.sleep(SETTLE_POLL_S)
        engine.refresh(force=True)


def one_line(error: BaseException) -> str:
    """An engine's error message in one line: its last non-empty line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__
