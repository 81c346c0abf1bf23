"""The ``cluster`` section: how ``fedhpg-cluster`` places a run on Slurm, Ray or this machine."""

from __future__ import annotations

from dataclasses import dataclass

from fedhpg.common.configuration.settings.checks import (
    check_choice,
    check_int,
    check_number,
    require,
)

CLUSTER_KINDS = ("auto", "slurm", "local", "ray")


@dataclass(kw_only=True)
class ClusterConfig:
    """``fedhpg-cluster``: the jobs of a federation on a cluster engine (submitit, Ray)."""

    kind: str = "auto"
    """'slurm', 'ray', 'local' or 'auto' (SLURM where sbatch is found, else local). 'local'
    runs the same jobs as processes on this machine (submitit's LocalExecutor); 'ray' runs
    them as tasks on a running Ray cluster."""
    partition: str | None = None
    """SLURM partition of every job; None = the cluster's default."""
    time_min: int = 60
    """Wall-clock limit of every job, in minutes (submitit's timeout_min; not Ray's)."""
    mem_gb: float = 4.0
    """Memory of every job, in GB (SLURM; Ray's memory resource)."""
    cpus_per_task: int = 1
    """CPU cores of every job (SLURM; Ray's num_cpus)."""
    gpus_per_host: int = 0
    """GPUs of every agent-side job (SLURM --gres=gpu:N, Ray num_gpus); with algo.device=cuda
    each agent host trains on its job's GPU. The server job gets none."""
    array_parallelism: int | None = None
    """Agent-side jobs of the array running at once; None = all. Never fewer than the jobs:
    the server waits for every agent before round 1."""
    folder: str = "submitit"
    """Where submitit keeps its job files and logs, relative to the run directory."""
    endpoint_timeout_s: float = 600.0
    """How long an agent job waits for the server job's endpoint file (queueing included)."""
    advertise_host: str | None = None
    """The address agents connect to; None = the server node's hostname on SLURM, its Ray node
    address on Ray (the server then binds every interface), loopback for 'local'."""
    address: str | None = None
    """Ray: the running cluster's address (host:port of its head); None = RAY_ADDRESS, else
    the Ray cluster started on this machine (ray start)."""


def validate_cluster(cluster: ClusterConfig) -> None:
    check_choice(cluster.kind, "cluster.kind", CLUSTER_KINDS)
    check_int(cluster.time_min, "cluster.time_min", low=1)
    check_number(cluster.mem_gb, "cluster.mem_gb", low=0.0, low_open=True)
    check_int(cluster.cpus_per_task, "cluster.cpus_per_task", low=1)
    check_int(cluster.gpus_per_host, "cluster.gpus_per_host", low=0)
    if cluster.array_parallelism is not None:
        check_int(cluster.array_parallelism, "cluster.array_parallelism", low=1)
    require(
        bool(cluster.folder.strip()) and not cluster.folder.startswith("/"),
        "cluster.folder",
        f"got {cluster.folder!r}, must be a path relative to the run directory",
    )
    check_number(cluster.endpoint_timeout_s, "cluster.endpoint_timeout_s", low=0.0, low_open=True)
