"""``fedhpg-cluster``: a federation's processes as jobs of a cluster engine, through submitit.

The server is one job and the agent-side processes one job array (SLURM; with
``cluster=local`` submitit's LocalExecutor runs the same jobs as processes here). Agents find
the server through its endpoint file in the run directory, which every node must see (a shared
filesystem, as on SLURM clusters): the server binds a free port and writes host and port there.
This process only submits and watches: it ends with the server job's status, reports each
failed agent job in one line, restarts a crashed agent job up to ``agent.max_restarts`` times,
and cancels whatever is still running when the server job ends or it is interrupted.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fedhpg.common.config import ConfigError, RunConfig
from fedhpg.common.runtime.cli import EXIT_RUN_ABORTED, EXIT_USAGE
from fedhpg.server.cluster_units import (
    ENDPOINT_NAME,
    STATUS_DIR,
    STOP_NAME,
    agent_commands,
    describe,
    run_unit,
    server_command,
)

logger = logging.getLogger(__name__)

POLL_S = 0.2
FINISH_GRACE_S = 10.0
"""After the server job ends, how long agent jobs may take to exit by themselves."""
STOP_WAIT_S = 5.0
"""How long jobs may take to end their commands once the stop file is there."""
CANCEL_WAIT_S = 5.0
"""How long a cancelled local job may take to be gone (submitit kills it after 1 s)."""
EXIT_INTERRUPTED = 130
INSTALL_HINT = "pip install 'fedhpg[cluster]'"


@dataclass
class AgentJob:
    """One agent-side unit and its current job (a restart submits a new one)."""

    command: list[str]
    job: Any
    restarts: int = 0
    finished: bool = False


@dataclass
class Placement:
    """The submitted jobs of one federation."""

    executor: Any
    endpoint: Path
    stop: Path
    server: Any
    agents: list[AgentJob] = field(default_factory=list)

    def jobs(self) -> list[Any]:
        return [self.server, *(a.job for a in self.agents)]


def check_placement(run: RunConfig, overrides: Sequence[str]) -> Path:
    """What ``fedhpg-cluster`` checks before it submits anything; returns the run directory."""
    from fedhpg.common.wire.security import check_launch_keys
    from fedhpg.server.assembly import check_run
    from fedhpg.server.run_dir import RunDirectory

    if run.resume:
        raise ConfigError(
            "resume",
            "fedhpg-cluster starts new runs; resume one with fedhpg-server resume=true "
            "server.out_dir=DIR and its agents (docs/running.md, Resuming)",
        )
    check_run(run, distributed=True)
    check_launch_keys(run)
    units = len(agent_commands(run, overrides))
    parallel = run.cluster.array_parallelism
    if parallel is not None and parallel < units:
        raise ConfigError(
            "cluster.array_parallelism",
            f"got {parallel}, below the {units} agent jobs: the server waits for every agent "
            "before round 1, so all must run at once",
        )
    run_dir = Path(run.server.out_dir or Path("runs") / time.strftime("%Y%m%d-%H%M%S"))
    RunDirectory.precheck(run_dir, resume=False)
    return run_dir.resolve()


def make_executor(run: RunConfig, run_dir: Path) -> Any:
    """submitit's AutoExecutor for ``cluster.kind``, its files and logs under the run dir."""
    import submitit

    cluster = run.cluster
    executor = submitit.AutoExecutor(
        folder=run_dir / cluster.folder / "%j",
        cluster=None if cluster.kind == "auto" else cluster.kind,
    )
    executor.update_parameters(
        timeout_min=cluster.time_min,
        mem_gb=cluster.mem_gb,
        cpus_per_task=cluster.cpus_per_task,
        slurm_partition=cluster.partition,
    )
    return executor


class SubmitError(Exception):
    """The engine refused a job (sbatch failed, say): one line, exit 1."""


def _one_line(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__


def submit(run: RunConfig, overrides: Sequence[str], run_dir: Path, executor: Any) -> Placement:
    """The server job, then the agent array (one ``batch()``: one sbatch --array on SLURM)."""
    bind_all = executor.cluster != "local"  # agents on other nodes; loopback when all are here
    endpoint = run_dir / ENDPOINT_NAME
    stop = run_dir / run.cluster.folder / STOP_NAME
    for old in (endpoint, stop):  # this run's jobs must not read an earlier run's files
        old.unlink(missing_ok=True)
    shutil.rmtree(stop.parent / STATUS_DIR, ignore_errors=True)
    executor.update_parameters(name="fedhpg-server")
    command = server_command(run, overrides, run_dir, bind_all=bind_all)
    try:
        server = executor.submit(run_unit, command, None, 0.0, str(stop))
    except Exception as error:  # the engine's own error (sbatch's message), whatever its type
        raise SubmitError(f"cannot submit the server job: {_one_line(error)}") from None
    logger.info("submitted the server as job %s (%s)", server.job_id, executor.cluster)
    placement = Placement(executor=executor, endpoint=endpoint, stop=stop, server=server)
    commands = agent_commands(run, overrides)
    executor.update_parameters(
        name="fedhpg-agent", slurm_array_parallelism=run.cluster.array_parallelism or len(commands)
    )
    try:
        with executor.batch():
            pending = [
                executor.submit(
                    run_unit, c, str(endpoint), run.cluster.endpoint_timeout_s, str(stop)
                )
                for c in commands
            ]
    except Exception as error:
        cancel_all(placement, graceful=False)  # likely still queued: nothing to stop yet
        raise SubmitError(
            f"cannot submit the agent jobs: {_one_line(error)} (the server job is cancelled)"
        ) from None
    placement.agents = [AgentJob(c, job) for c, job in zip(commands, pending, strict=True)]
    logger.info("submitted %d agent jobs: %s", len(pending), ", ".join(j.job_id for j in pending))
    return placement


def _status(placement: Placement, job: Any) -> tuple[int | None, str]:
    """A finished job's exit status, from the JSON its job wrote (never submitit's result
    pickle); None, and why, if the job ended before its command did (killed, timed out)."""
    path = placement.stop.parent / STATUS_DIR / f"{job.job_id}.json"
    try:
        return int(json.loads(path.read_text(encoding="utf-8"))["status"]), ""
    except (OSError, ValueError, KeyError, TypeError):
        return None, f"it ended before its command did (job state {job.state})"


def _log_of(job: Any) -> str:
    return str(job.paths.stderr)


def _watch_agents(run: RunConfig, placement: Placement) -> bool:
    """Restart crashed agent jobs (as fedhpg-run restarts processes); False once one has no
    restarts left."""
    for agent in placement.agents:
        if agent.finished or not agent.job.done():
            continue
        status, why = _status(placement, agent.job)
        if status in (0, EXIT_RUN_ABORTED):  # done, or the server ended the run: it tells how
            agent.finished = True
            continue
        what = f"exited with status {status}" if status is not None else f"failed: {why}"
        if agent.restarts >= run.agent.max_restarts:
            logger.error(
                "agent job %s (%s) %s; stopping the federation (log: %s)",
                agent.job.job_id, describe(agent.command), what, _log_of(agent.job),
            )  # fmt: skip
            agent.finished = True
            return False
        agent.restarts += 1
        placement.executor.update_parameters(name="fedhpg-agent")
        agent.job = placement.executor.submit(
            run_unit,
            agent.command,
            str(placement.endpoint),
            run.cluster.endpoint_timeout_s,
            str(placement.stop),
        )
        logger.warning(
            "agent job of %s %s; resubmitted as job %s (%d of %d restarts, agent.max_restarts)",
            describe(agent.command), what, agent.job.job_id, agent.restarts, run.agent.max_restarts,
        )  # fmt: skip
    return True


def supervise(run: RunConfig, placement: Placement) -> int:
    """Until the server job ends: its status (1 if it failed or an agent job did)."""
    while not placement.server.done():
        if not _watch_agents(run, placement):
            return 1
        time.sleep(POLL_S)
    status, why = _status(placement, placement.server)
    server = f"the server job {placement.server.job_id}"
    if status is None:
        sys.stderr.write(f"error: {server} failed: {why} (log: {_log_of(placement.server)})\n")
        return 1
    if status != 0:  # its agents are stopped at once: nothing is left for them to do
        sys.stderr.write(
            f"error: {server} exited with status {status} (log: {_log_of(placement.server)})\n"
        )
        return status if 0 < status < 128 else 1  # killed by a signal: negative
    deadline = time.monotonic() + FINISH_GRACE_S
    while time.monotonic() < deadline and not all(a.job.done() for a in placement.agents):
        time.sleep(POLL_S)
    failed = 0
    for agent in placement.agents:
        if not agent.job.done():
            logger.error("agent job %s did not end after the run; cancelling it", agent.job.job_id)
            failed += 1
            continue
        code, reason = _status(placement, agent.job)
        if code not in (0, EXIT_RUN_ABORTED):
            failed += 1
            what = f"exited with status {code}" if code is not None else f"failed: {reason}"
            logger.error(
                "agent job %s (%s) %s (log: %s)",
                agent.job.job_id, describe(agent.command), what, _log_of(agent.job),
            )  # fmt: skip
    return 1 if failed else 0


def cancel_all(placement: Placement, *, graceful: bool = True) -> None:
    """Stop every job still running: first through the stop file (each job ends its command,
    the job completes) if ``graceful``, then by cancelling what is left; local jobs are
    waited for."""
    running = [job for job in placement.jobs() if not job.done()]
    if not running:
        return
    placement.stop.touch()
    deadline = time.monotonic() + (STOP_WAIT_S if graceful else 0.0)
    while time.monotonic() < deadline and not all(job.done() for job in running):
        time.sleep(0.05)
    left = [job for job in running if not job.done()]
    for job in left:
        try:
            job.cancel(check=False)
        except Exception as error:  # scancel missing or failing: say so, go on with the rest
            logger.error("cannot cancel job %s: %s", job.job_id, error)
    if placement.executor.cluster == "local":
        deadline = time.monotonic() + CANCEL_WAIT_S
        while time.monotonic() < deadline and not all(job.done() for job in left):
            time.sleep(0.05)
    logger.info(
        "stopped jobs %s%s",
        ", ".join(job.job_id for job in running),
        f" (cancelled {', '.join(job.job_id for job in left)})" if left else "",
    )


def place(run: RunConfig, overrides: Sequence[str], run_dir: Path, executor: Any) -> int:
    """Submit the federation, watch it, cancel what is left; the exit status."""
    new = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    placement: Placement | None = None
    previous = signal.getsignal(signal.SIGTERM)

    def interrupt(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    try:
        placement = submit(run, overrides, run_dir, executor)
        status = supervise(run, placement)
        if status == 0:
            sys.stdout.write(f"run directory: {run_dir}\n")
        return status
    except SubmitError as error:
        sys.stderr.write(f"error: {error}\n")
        if new:  # nothing ran in it: leave nothing behind
            shutil.rmtree(run_dir, ignore_errors=True)
        return 1
    except KeyboardInterrupt:
        logger.warning("interrupted: cancelling the federation's jobs")
        return EXIT_INTERRUPTED
    finally:
        if placement is not None:
            cancel_all(placement)
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> None:
    """Check everything (one-line errors, exit 2, nothing submitted), then place the run."""
    from fedhpg.common.runtime.cli import (
        HELP_FLAGS,
        answer_version,
        compose,
        fail,
        own_overrides,
        setup_logging,
        unknown_flag,
    )

    args = list(sys.argv[1:] if argv is None else argv)
    answer_version("fedhpg-cluster", args)
    if any(a in HELP_FLAGS for a in args):
        from fedhpg.common.runtime.help import help_text

        sys.stdout.write(help_text("fedhpg-cluster"))
        sys.exit(0)
    if any(a in ("-m", "--multirun") for a in args):
        sys.exit(
            fail(
                ConfigError(
                    "-m",
                    "fedhpg-cluster places one federation; sweep with fedhpg-run -m ... "
                    "hydra/launcher=submitit_slurm (docs/clusters.md)",
                )
            )
        )
    flag = unknown_flag(args, known=())
    if flag is not None:
        sys.exit(fail(flag))
    setup_logging()
    overrides = own_overrides(args)
    try:
        run = compose(overrides)
        run_dir = check_placement(run, overrides)
    except ConfigError as error:
        sys.exit(fail(error))
    try:
        import submitit  # noqa: F401  (the optional dependency: checked before anything starts)
    except ImportError:
        sys.stderr.write(f"error: fedhpg-cluster needs submitit: {INSTALL_HINT}\n")
        sys.exit(EXIT_USAGE)
    try:
        executor = make_executor(run, run_dir)
    except (RuntimeError, ValueError) as error:  # e.g. kind=slurm where SLURM is not
        sys.exit(fail(ConfigError("cluster.kind", f"{run.cluster.kind}: {_one_line(error)}")))
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # jobs inherit it (local; SLURM exports)
    sys.exit(place(run, overrides, run_dir, executor))
