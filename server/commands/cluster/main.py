"""``fedhpg-cluster``: a federation's processes as jobs of a cluster engine.

The server is one job and the agent-side processes one job array: on SLURM through submitit
(``cluster=slurm``; ``cluster=local`` runs the same jobs as processes here), or as tasks on a
running Ray cluster (``cluster=ray``). Agents find the server through its endpoint file in the
run directory, which every node must see (a shared filesystem, as on SLURM clusters): the
server binds a free port and writes host and port there. This process only submits and
watches, the same way on every engine (:mod:`.engines`): it shows each round as the
server writes it to the run directory and the final table of the unified policy's evaluation,
ends with the server job's status, reports each failed agent job in one line, restarts a
crashed agent job up to ``agent.max_restarts`` times, and stops whatever is still running when
the server job ends or it is interrupted, waiting until the engine reports it gone.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime.cli import (
    EXIT_RUN_ABORTED,
    EXIT_USAGE,
    HELP_FLAGS,
    Interrupted,
    answer_version,
    compose,
    fail,
    repeated_key,
    setup_logging,
    stop_signals,
    unknown_flag,
)
from fedhpg.common.runtime.composition import own_overrides
from fedhpg.common.runtime.help import help_text
from fedhpg.common.runtime.progress import Progress
from fedhpg.common.runtime.run_files import METRICS_NAME
from fedhpg.common.wire.security import check_launch_keys
from fedhpg.server.commands.cluster.engines import (
    Engine,
    Job,
    SubmitError,
    SubmititEngine,
    UnitFiles,
    one_line,
    settle,
)
from fedhpg.server.commands.cluster.ray_engine import RayEngine
from fedhpg.server.commands.cluster.units import (
    ENDPOINT_NAME,
    STOP_NAME,
    agent_commands,
    describe,
    server_command,
)
from fedhpg.server.report import evaluation_of
from fedhpg.server.run_dir import RunDirectory

logger = logging.getLogger(__name__)

POLL_S = 0.2
FINISH_GRACE_S = 10.0
"""After the server job ends, how long agent jobs may take to exit by themselves."""
STOP_WAIT_S = 5.0
"""How long jobs may take to end their commands once the stop file is there."""
CANCEL_WAIT_S = {"local": 5.0, "slurm": 60.0, "ray": 30.0}
"""How long cancelled jobs may take to be reported gone: submitit kills a local job after 1 s;
SLURM signals a job's processes, then kills them after its KillWait (30 s by default)."""


@dataclass
class AgentJob:
    """One agent-side unit and its current job (a restart submits a new one)."""

    command: list[str]
    job: Job
    restarts: int = 0
    finished: bool = False


@dataclass
class Placement:
    """The submitted jobs of one federation."""

    engine: Engine
    stop: Path
    server: Job
    agents: list[AgentJob] = field(default_factory=list)

    def jobs(self) -> list[Job]:
        return [self.server, *(a.job for a in self.agents)]


AGENT_PLACED_KEYS = ("agent.index", "agent.first", "agent.count")
"""Keys that :func:`~fedhpg.server.commands.cluster.units.agent_commands` gives each agent unit."""


def check_placement(run: RunConfig, overrides: Sequence[str]) -> Path:
    """What ``fedhpg-cluster`` checks before it submits anything; returns the run directory."""
    from fedhpg.server.assembly import check_run

    if run.resume:
        raise ConfigError(
            "resume",
            "fedhpg-cluster starts new runs; resume one with fedhpg-server resume=true "
            "server.out_dir=DIR and its agents (docs/running.md, Resuming)",
        )
    placed = [o.split("=", 1)[0].lstrip("+") for o in overrides]
    for key in AGENT_PLACED_KEYS:
        if key in placed:  # each agent job's command line gives it once: its own
            raise ConfigError(key, "fedhpg-cluster sets it for each agent job; leave it out")
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


def unit_files(run: RunConfig, run_dir: Path) -> UnitFiles:
    return UnitFiles(
        endpoint=run_dir / ENDPOINT_NAME,
        stop=run_dir / run.cluster.folder / STOP_NAME,
        endpoint_timeout_s=run.cluster.endpoint_timeout_s,
    )


def make_engine(run: RunConfig, run_dir: Path) -> Engine:
    """The engine ``cluster.kind`` names, its files and logs under the run directory."""
    if run.cluster.kind == "ray":
        return RayEngine(run, run_dir, unit_files(run, run_dir))
    return SubmititEngine(run, run_dir, unit_files(run, run_dir))


def submit(run: RunConfig, overrides: Sequence[str], run_dir: Path, engine: Engine) -> Placement:
    """The server job, then the agent array (one ``sbatch --array`` on SLURM)."""
    files = unit_files(run, run_dir)
    for old in (files.endpoint, files.stop):  # this run's jobs must not read an earlier run's
        old.unlink(missing_ok=True)
    shutil.rmtree(files.status_dir, ignore_errors=True)
    commands = agent_commands(run, overrides)
    engine.check_room(len(commands))
    server = engine.submit_server(server_command(run, overrides, run_dir, bind_all=engine.bind_all))
    logger.info("submitted the server as job %s (%s)", server.job_id, engine.kind)
    placement = Placement(engine=engine, stop=files.stop, server=server)
    try:
        pending = engine.submit_agents(commands)
    except SubmitError as error:
        cancel_all(placement, graceful=False)  # likely still queued: nothing to stop yet
        raise SubmitError(f"{error} (the server job is cancelled)") from None
    placement.agents = [AgentJob(c, job) for c, job in zip(commands, pending, strict=True)]
    logger.info("submitted %d agent jobs: %s", len(pending), ", ".join(j.job_id for j in pending))
    return placement


def _watch_agents(run: RunConfig, placement: Placement) -> bool:
    """Restart crashed agent jobs (as fedhpg-run restarts processes); False once one has no
    restarts left."""
    placement.engine.refresh()
    for agent in placement.agents:
        if agent.finished or not agent.job.done():
            continue
        status, why = agent.job.status()
        if status in (0, EXIT_RUN_ABORTED):  # done, or the server ended the run: it tells how
            agent.finished = True
            continue
        what = f"exited with status {status}" if status is not None else f"failed: {why}"
        if agent.restarts >= run.agent.max_restarts:
            logger.error(
                "agent job %s (%s) %s; stopping the federation (log: %s)",
                agent.job.job_id, describe(agent.command), what, agent.job.log,
            )  # fmt: skip
            agent.finished = True
            return False
        agent.restarts += 1
        agent.job = placement.engine.submit_agent(agent.command)
        logger.warning(
            "agent job of %s %s; resubmitted as job %s (%d of %d restarts, agent.max_restarts)",
            describe(agent.command), what, agent.job.job_id, agent.restarts, run.agent.max_restarts,
        )  # fmt: skip
    return True


class RoundProgress:
    """The server job's rounds as they land in the run directory's metrics.jsonl (which this
    node sees, as every node does), on the progress display ``fedhpg-run`` shows."""

    def __init__(self, run: RunConfig, run_dir: Path) -> None:
        from fedhpg.common.heterogeneity.variants import variant_of

        self.run = run
        self.metrics = run_dir / METRICS_NAME
        self.has_goal = bool(variant_of(run, 0).has_goal)
        self._offset = 0
        self._bar: Progress | None = None

    def poll(self) -> None:
        """Show the rounds written since the last poll (whole lines only)."""
        from fedhpg.server.serving import round_status

        try:
            with self.metrics.open("rb") as handle:
                handle.seek(self._offset)
                written = handle.read()
        except OSError:  # not written yet
            return
        end = written.rfind(b"\n") + 1
        self._offset += end
        for line in written[:end].splitlines():
            try:
                record = json.loads(line)
                number, round_time_s = int(record["round"]), float(record["round_time_s"])
                evaluation = evaluation_of(record["eval"]) if record.get("eval") else None
            except (ValueError, KeyError, TypeError):  # not a round's record: not ours to judge
                continue
            if self._bar is None:
                self._bar = Progress(self.run.rounds, "rounds", done=number - 1)
            self._bar.update(1, round_status(round_time_s, evaluation, has_goal=self.has_goal))

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def report(self) -> None:
        """The unified policy's last evaluation per agent from summary.json, as the server
        prints it, then where the run directory is."""
        from fedhpg.server.serving import print_report

        run_dir = self.metrics.parent
        try:
            summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
            evaluation = evaluation_of(summary["eval"]) if summary.get("eval") else None
            last_round, agent_ids = int(summary["final_eval_round"]), list(summary["variants"])
        except (OSError, ValueError, KeyError, TypeError) as error:
            logger.warning("cannot read the run's summary.json: %s", error)
            evaluation, last_round, agent_ids = None, 0, []
        print_report(
            self.run,
            last_round=last_round,
            evaluation=evaluation,
            agent_ids=agent_ids,
            has_goal=self.has_goal,
            out_dir=run_dir,
        )


def supervise(run: RunConfig, placement: Placement, rounds: RoundProgress | None = None) -> int:
    """Until the server job ends: its status (1 if it failed or an agent job did); the rounds
    are shown as they complete."""
    while not placement.server.done():
        if not _watch_agents(run, placement):
            return 1
        if rounds is not None:
            rounds.poll()
        time.sleep(POLL_S)
    if rounds is not None:
        rounds.poll()
        rounds.close()
    status, why = placement.server.status()
    server = f"the server job {placement.server.job_id}"
    if status is None:
        sys.stderr.write(f"error: {server} failed: {why} (log: {placement.server.log})\n")
        return 1
    if status != 0:  # its agents are stopped at once: nothing is left for them to do
        sys.stderr.write(
            f"error: {server} exited with status {status} (log: {placement.server.log})\n"
        )
        return status if 0 < status < 128 else 1  # killed by a signal: negative
    deadline = time.monotonic() + FINISH_GRACE_S
    while time.monotonic() < deadline and not all(a.job.done() for a in placement.agents):
        time.sleep(POLL_S)
        placement.engine.refresh()
    failed = 0
    for agent in placement.agents:
        if not agent.job.done():
            logger.error("agent job %s did not end after the run; cancelling it", agent.job.job_id)
            failed += 1
            continue
        code, reason = agent.job.status()
        if code not in (0, EXIT_RUN_ABORTED):
            failed += 1
            what = f"exited with status {code}" if code is not None else f"failed: {reason}"
            logger.error(
                "agent job %s (%s) %s (log: %s)",
                agent.job.job_id, describe(agent.command), what, agent.job.log,
            )  # fmt: skip
    return 1 if failed else 0


def cancel_all(placement: Placement, *, graceful: bool = True) -> None:
    """Stop every job still running: first through the stop file (each job ends its command,
    the job completes) if ``graceful``, then by cancelling what is left; then wait until the
    engine reports every one gone."""
    engine = placement.engine
    running = [job for job in placement.jobs() if not job.done()]
    if not running:
        return
    placement.stop.parent.mkdir(parents=True, exist_ok=True)
    placement.stop.touch()
    left = settle(engine, running, STOP_WAIT_S if graceful else 0.0)
    for job in left:
        try:
            job.cancel()
        except Exception as error:  # scancel missing or failing: say so, go on with the rest
            logger.error("cannot cancel job %s: %s", job.job_id, error)
    lingering = settle(engine, left, CANCEL_WAIT_S.get(engine.kind, 30.0))
    logger.info(
        "stopped jobs %s%s",
        ", ".join(job.job_id for job in running),
        f" (cancelled {', '.join(job.job_id for job in left)})" if left else "",
    )
    if lingering:
        logger.error(
            "jobs %s still not reported ended by %s",
            ", ".join(job.job_id for job in lingering), engine.kind,
        )  # fmt: skip


def place(run: RunConfig, overrides: Sequence[str], run_dir: Path, engine: Engine) -> int:
    """Submit the federation, watch it, stop what is left; the exit status (128 + the
    signal's number when SIGINT or SIGTERM stopped it, even one started with SIGINT ignored,
    as a shell's background job is)."""
    new = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    placement: Placement | None = None
    rounds = RoundProgress(run, run_dir)
    with stop_signals():
        try:
            placement = submit(run, overrides, run_dir, engine)
            status = supervise(run, placement, rounds)
            if status == 0:
                rounds.report()
            return status
        except SubmitError as error:
            sys.stderr.write(f"error: {error}\n")
            if new and placement is None:  # nothing ran in it: leave nothing behind
                shutil.rmtree(run_dir, ignore_errors=True)
            return 1
        except Interrupted as interrupted:
            logger.warning("interrupted: cancelling the federation's jobs")
            return interrupted.status
        finally:
            if placement is not None:
                cancel_all(placement)
            engine.close()


def main(argv: Sequence[str] | None = None) -> None:
    """Check everything (one-line errors, exit 2, nothing submitted), then place the run."""
    args = list(sys.argv[1:] if argv is None else argv)
    answer_version("fedhpg-cluster", args)
    if any(a in HELP_FLAGS for a in args):
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
    flag = unknown_flag(args, known=()) or repeated_key(args)
    if flag is not None:
        sys.exit(fail(flag))
    setup_logging()
    overrides = own_overrides(args)
    try:
        run = compose(overrides)
        run_dir = check_placement(run, overrides)
    except ConfigError as error:
        sys.exit(fail(error))
    package = "ray" if run.cluster.kind == "ray" else "submitit"
    try:  # the optional dependency: checked before anything starts
        __import__(package)
    except ImportError:
        extra = "ray" if package == "ray" else "cluster"
        sys.stderr.write(f"error: fedhpg-cluster needs {package}: pip install 'fedhpg[{extra}]'\n")
        sys.exit(EXIT_USAGE)
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # jobs inherit it (local; SLURM, Ray pass it)
    try:
        engine = make_engine(run, run_dir)
    except (RuntimeError, ValueError, SubmitError) as error:  # e.g. kind=slurm where SLURM is not
        sys.exit(fail(ConfigError("cluster.kind", f"{run.cluster.kind}: {one_line(error)}")))
    sys.exit(place(run, overrides, run_dir, engine))
