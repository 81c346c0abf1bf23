"""``cluster=ray``: a federation's units as tasks on a running Ray cluster.

Each unit (the server, each agent-side process) is one Ray task that runs
:func:`~fedhpg.server.commands.cluster.units.run_unit`, as a SLURM job does: it waits for the
server's endpoint file, starts the command as its child (which dies with the task's worker), and
returns the command's exit status. The wire stays ZeroMQ, between the commands; Ray only places
them. Tasks ask for ``cluster.cpus_per_task`` CPUs, ``cluster.mem_gb`` of memory and, for the agent
side, ``cluster.gpus_per_host`` GPUs (Ray then sets the task's CUDA_VISIBLE_DEVICES, which the
command inherits); they are spread over the nodes. The server binds every interface and
advertises its Ray node's address. Restarts, stopping and cancelling are the placement's own
(:mod:`.main`): a task is never retried by Ray.

The run directory must be on a filesystem every node sees (the endpoint, stop and log files),
and every node must run the Python environment this package is installed in. This is the only
module that imports Ray, and only ``fedhpg-cluster cluster=ray`` imports it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.server.commands.cluster.engines import Job, SubmitError, UnitFiles, one_line
from fedhpg.server.commands.cluster.units import run_unit

PASSED_ENV_PREFIXES = ("FEDHPG_", "OMP_", "MKL_", "NUMBA_", "PYTHONPATH")
"""The driver's variables every task's command gets (a Ray worker starts with the node's own
environment): the log level, thread counts, numba's cache, where plugins are imported from."""
INSTALL_HINT = "pip install 'fedhpg[ray]'"


def ray_unit(
    command: list[str],
    endpoint_file: str | None,
    timeout_s: float,
    stop_file: str,
    job_id: str,
    log_file: str,
    cwd: str,
    env: dict[str, str],
    advertise: bool,
) -> int:
    """The task: :func:`run_unit` in a Ray worker; the server advertises its node's address."""
    if advertise:
        import ray

        command = [*command, f"cluster.advertise_host={ray.util.get_node_ip_address()}"]
    return run_unit(
        command, endpoint_file, timeout_s, stop_file,
        job_id=job_id, log_file=log_file, cwd=cwd, env=env,
    )  # fmt: skip


class RayJob:
    """One task; its exit status is the task's result."""

    def __init__(self, job_id: str, ref: Any, log: Path) -> None:
        self._job_id = job_id
        self.ref = ref
        self._log = log

    @property
    def job_id(self) -> str:
        return self._job_id

    @property
    def log(self) -> str:
        return str(self._log)

    def done(self) -> bool:
        import ray

        ready, _ = ray.wait([self.ref], timeout=0)
        return bool(ready)

    def status(self) -> tuple[int | None, str]:
        import ray

        try:
            return int(ray.get(self.ref, timeout=0)), ""
        except ray.exceptions.TaskCancelledError:
            return None, "it ended before its command did (task cancelled)"
        except ray.exceptions.RayError as error:
            return None, f"it ended before its command did ({one_line(error)})"

    def cancel(self) -> None:
        import ray

        ray.cancel(self.ref, force=True)  # its worker is killed, the command with it


class RayEngine:
    """Units as Ray tasks, on the cluster at ``cluster.address`` (else RAY_ADDRESS, else the
    one started on this machine)."""

    kind = "ray"
    bind_all = True

    def __init__(self, run: RunConfig, run_dir: Path, files: UnitFiles) -> None:
        import ray

        cluster = run.cluster
        address = cluster.address or os.environ.get("RAY_ADDRESS") or "auto"
        try:
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise SubmitError(
                f"cannot reach a Ray cluster at {address}: {one_line(error)}"
            ) from None
        self.files = files
        self.folder = run_dir / cluster.folder
        self.cpus = cluster.cpus_per_task
        self.gpus = cluster.gpus_per_host
        self.memory = int(cluster.mem_gb * 1024**3)
        self.env = {
            name: value for name, value in os.environ.items()
            if name.startswith(PASSED_ENV_PREFIXES)
        }  # fmt: skip
        self._remote = ray.remote(ray_unit)
        self._submitted = 0

    def check_room(self, agent_units: int) -> None:
        """Every unit must run at once (the server waits for every agent before round 1): a
        cluster without the CPUs, GPUs or memory for all of them is refused up front, since Ray
        would leave the rest pending."""
        import ray

        have = ray.cluster_resources()
        want = {
            "CPU": self.cpus * (agent_units + 1),
            "GPU": self.gpus * agent_units,
            "memory": self.memory * (agent_units + 1),
        }
        for name, amount in want.items():
            if amount > have.get(name, 0):
                key = {"CPU": "cpus_per_task", "GPU": "gpus_per_host", "memory": "mem_gb"}[name]
                unit = 1024**3 if name == "memory" else 1  # memory in GiB
                raise SubmitError(
                    f"the Ray cluster has {have.get(name, 0) / unit:g} {name}, the run needs "
                    f"{amount / unit:g} at once (cluster.{key})"
                )

    def _submit(self, name: str, command: list[str], endpoint: Path | None, gpus: int) -> Job:
        self._submitted += 1
        job_id = str(self._submitted)
        log = self.folder / job_id / f"{job_id}_log.err"
        options: dict[str, Any] = {
            "name": name,
            "num_cpus": self.cpus,
            "num_gpus": gpus,
            "memory": self.memory,
            "max_retries": 0,  # a crashed unit is the placement's to restart
            "scheduling_strategy": "SPREAD",
        }
        try:
            ref = self._remote.options(**options).remote(
                command,
                None if endpoint is None else str(endpoint),
                self.files.endpoint_timeout_s if endpoint is not None else 0.0,
                str(self.files.stop),
                job_id,
                str(log),
                str(Path.cwd()),
                self.env,
                endpoint is None,  # the server advertises its node's address
            )
        except Exception as error:  # Ray's own error, whatever its type
            raise SubmitError(f"cannot submit the {name} task: {one_line(error)}") from None
        return RayJob(job_id, ref, log)

    def submit_server(self, command: list[str]) -> Job:
        return self._submit("fedhpg-server", command, None, 0)

    def submit_agents(self, commands: Sequence[list[str]]) -> list[Job]:
        return [self.submit_agent(command) for command in commands]

    def submit_agent(self, command: list[str]) -> Job:
        return self._submit("fedhpg-agent", command, self.files.endpoint, self.gpus)

    def refresh(self, *, force: bool = False) -> None:
        return None  # ray.wait asks the cluster each time

    def close(self) -> None:
        import ray

        ray.shutdown()
