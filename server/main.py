"""``fedhpg-server``: bind, wait for the K agents, run the rounds, write the run directory."""

from __future__ import annotations

import json
import logging
import socket as socket_module
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import zmq

from fedhpg.common.components import agent_profile, resolve_algorithm
from fedhpg.common.config import (
    ConfigError,
    RunConfig,
    dictated_settings,
    fixed_difference,
    to_dict,
)
from fedhpg.common.runtime.cli import run_entry
from fedhpg.common.runtime.progress import Progress
from fedhpg.common.types import EvaluationStats
from fedhpg.common.variants import run_variants, variant_digest, variant_of
from fedhpg.common.wire.security import handshake_failure_logger, secure_server_socket
from fedhpg.common.wire.transport import (
    batch_message_cap,
    bind_endpoint,
    configure_socket,
    max_message_bytes,
    single_message_bytes,
)
from fedhpg.common.worker import initial_theta
from fedhpg.envs.base import EnvVariant
from fedhpg.server.checkpoint import (
    Checkpoint,
    latest_valid_checkpoint,
    save_checkpoint,
    write_atomic,
)
from fedhpg.server.connections import ConnectionGuard, connection_budget
from fedhpg.server.coordinator import Coordinator, RoundCallback, RoundRecord, RunProgress
from fedhpg.server.metrics import MetricsWriter, tensorboard_sink
from fedhpg.server.pools import FederationError
from fedhpg.server.pools.zmq_pool import ZmqAgentPool
from fedhpg.server.report import evaluation_table
from fedhpg.server.rounds import check_distributed_policy
from fedhpg.server.run_dir import RunDirectory, RunDirectoryError, claimed
from fedhpg.server.strategies import Strategy, make_strategy, validate_strategy
from fedhpg.server.validation import UpdateCheck

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ServerResult:
    theta: torch.Tensor
    out_dir: Path
    last_evaluation: dict[str, EvaluationStats] | None


def default_out_dir() -> Path:
    return Path("runs") / time.strftime("%Y%m%d-%H%M%S")


def _progress_callback(
    progress: Progress, *, has_goal: bool
) -> Callable[[RoundRecord, torch.Tensor], None]:
    def update(record: RoundRecord, _: torch.Tensor) -> None:
        status = f"round {record.round_time_s:.2f}s"
        if record.eval:
            success = [e.success_rate for e in record.eval.values()]
            returns = [e.return_mean for e in record.eval.values()]
            mean_return = sum(returns) / len(returns)
            status += " | eval "
            status += f"success min {min(success):.2f}, " if has_goal else ""
            status += f"mean return {mean_return:.3f}"
        progress.update(1, status)

    return update


def checkpoint_callback(
    run: RunConfig,
    directory: Path,
    progress: RunProgress,
    counters: Callable[[], dict[str, int]],
) -> RoundCallback:
    settings = to_dict(run)

    def save(record: RoundRecord, theta: torch.Tensor) -> None:
        checkpoint = Checkpoint(
            round=record.round,
            theta=theta,
            config=settings,
            metrics_lines=record.round,
            state={
                "trajectories_per_agent": progress.trajectories_per_agent,
                "elapsed_s": progress.elapsed_s,
                "counters": counters(),
                **({"plan": progress.plan_state} if progress.plan_state else {}),
            },
            strategy=progress.strategy_state,
            schedule=progress.schedule_state,
        )
        try:
            save_checkpoint(directory, checkpoint)
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write the checkpoint of round {record.round} in {directory}: "
                f"{error.strerror or error}; the newest complete checkpoint is kept"
            ) from None

    return save


def resume_point(
    run: RunConfig, run_dir: RunDirectory, strategy: Strategy[Any]
) -> tuple[torch.Tensor, RunProgress, dict[str, int]]:
    """θ̃, the run's progress and its counters from the newest valid checkpoint. Everything is
    checked first (the config, rounds, the strategy's state, metrics.jsonl up to the
    checkpoint); only then is metrics.jsonl cut back to the checkpoint."""
    out_dir = run_dir.path
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    if checkpoint is None:
        raise ConfigError("resume", f"no valid checkpoint in {out_dir / 'checkpoints'}")
    changed = fixed_difference(checkpoint.config, to_dict(run))
    if changed is not None:
        message = str(changed).split(": ", 1)[1]
        raise ConfigError(changed.key, f"{message} (the checkpoint in {out_dir})")
    planned = int(checkpoint.config.get("rounds", checkpoint.round))
    if run.rounds < planned:
        raise ConfigError(
            "rounds",
            f"got {run.rounds}, but the run in {out_dir} has rounds={planned} (checkpointed at "
            f"round {checkpoint.round}); a resume may keep or raise rounds, never lower them",
        )
    if strategy.state().scalars and not checkpoint.strategy.scalars:
        raise ConfigError(
            "resume",
            f"the checkpoint holds no state of strategy {strategy.name!r}; it cannot be resumed",
        )
    kept = run_dir.checked_metrics(checkpoint.metrics_lines)
    write_atomic(run_dir.metrics, "".join(line + "\n" for line in kept).encode())
    logger.warning("resuming %s after round %d", out_dir, checkpoint.round)
    progress = RunProgress(
        next_round=checkpoint.round + 1,
        trajectories_per_agent=float(checkpoint.state.get("trajectories_per_agent", 0.0)),
        elapsed_s=float(checkpoint.state.get("elapsed_s", 0.0)),
        strategy_state=checkpoint.strategy,
        plan_state=dict(checkpoint.state.get("plan", {})),
        schedule_state=checkpoint.schedule,
    )
    counters = checkpoint.state.get("counters", {})
    return checkpoint.theta, progress, {k: int(v) for k, v in dict(counters).items()}


def message_cap(run: RunConfig, num_params: int) -> int:
    """The largest message this run's agents may send: a header and θ_k, or an agent host's
    batch of θs (ZMQ_MAXMSGSIZE and the codec's cap). ``server.max_message_mb`` may lower it
    only as far as one θ."""
    needed = single_message_bytes(num_params)
    configured = max_message_bytes(run.server)
    if configured < needed:
        raise ConfigError(
            "server.max_message_mb",
            f"got {run.server.max_message_mb:g}, below the {needed / 2**20:.3g} MiB this run's "
            f"updates need (θ of {num_params} float32 and a header of up to 1 MiB)",
        )
    return batch_message_cap(configured, num_params)


def run_digests(run: RunConfig) -> list[str]:
    """Every agent's :func:`variant_digest`, what the server checks each hello against. The
    variants are made a chunk at a time and dropped: K short strings stay (~1 MB at K=10 000)."""
    return [variant_digest(run, variant) for variant in run_variants(run)]


def serve(
    run: RunConfig,
    *,
    out_dir: Path,
    on_bound: Callable[[str], None] | None = None,
    show_progress: bool = True,
) -> ServerResult:
    """Run one federation as its server; returns the final θ̃_T."""
    validate_strategy(run)
    check_distributed_policy(run)
    strategy = make_strategy(run.strategy, run=run)
    first = variant_of(run, 0)
    theta, progress = initial_theta(first, run), RunProgress()
    counters: dict[str, int] = {}
    cap = message_cap(run, int(theta.numel()))
    with claimed(out_dir, resume=bool(run.resume)) as run_dir:
        if run.resume:
            theta, progress, counters = resume_point(run, run_dir, strategy)
            if run.server.round_policy == "buffered" and progress.schedule_state is None:
                raise ConfigError(
                    "server.round_policy",
                    "got 'buffered', but the checkpoint was written by synchronous rounds "
                    "(it holds no agent's round count); resume with the run's own round policy",
                )
        write_atomic(out_dir / "config.json", json.dumps(to_dict(run), indent=2).encode())
        return _serve_claimed(
            run,
            run_dir=run_dir,
            strategy=strategy,
            first=first,
            theta=theta,
            progress=progress,
            counters=counters,
            cap=cap,
            on_bound=on_bound,
            show_progress=show_progress,
        )


def _serve_claimed(
    run: RunConfig,
    *,
    run_dir: RunDirectory,
    strategy: Strategy[Any],
    first: EnvVariant,
    theta: torch.Tensor,
    progress: RunProgress,
    counters: dict[str, int],
    cap: int,
    on_bound: Callable[[str], None] | None,
    show_progress: bool,
) -> ServerResult:
    out_dir = run_dir.path
    context = zmq.Context()
    socket = context.socket(zmq.ROUTER)
    configure_socket(socket, run.server)
    socket.setsockopt(zmq.MAXMSGSIZE, cap)
    security = secure_server_socket(socket, context, run.security)  # CURVE+ZAP, pre-bind
    socket.setsockopt(zmq.ROUTER_MANDATORY, 1)
    connections = ConnectionGuard(
        socket,
        max_inflight_bytes=2 * cap + 64 * 1024,
        hello_timeout_s=run.server.hello_timeout_s,
        max_connections=connection_budget(max_connections(run)),
        on_handshake_failed=handshake_failure_logger(curve=run.security.curve),
    ).start()  # before bind: every connection is seen
    pool = ZmqAgentPool(
        socket=socket,
        num_agents=run.agents.num_agents,
        check=UpdateCheck(
            num_params=int(theta.numel()), max_update_norm=run.server.max_update_norm
        ),
        env_signature=first.signature(),  # builds an env: once, not per agent
        variant_digests=run_digests(run),
        run_settings=dictated_settings(run),  # security: only dictated keys leave the server
        run_id=uuid.uuid4().hex[:12],
        max_bytes=cap,
        settings=run.server,
        guard=connections,
    )
    pool.restore_counters(counters)
    metrics = MetricsWriter(run_dir.metrics)
    board = tensorboard_sink(
        run.server.tensorboard,
        out_dir,
        first_round=progress.next_round,
        theta=theta,
        per_agent=run.agents.num_agents <= run.server.tensorboard_agents,
    )
    last_eval: dict[str, Any] = {}

    def keep_eval(record: RoundRecord, _: torch.Tensor) -> None:
        if record.eval:
            last_eval["round"], last_eval["eval"] = record.round, record.eval

    callbacks: list[RoundCallback] = [
        metrics,
        checkpoint_callback(run, out_dir / "checkpoints", progress, pool.counters),
        keep_eval,
        *([board] if board is not None else []),
    ]
    bar: Progress | None = None
    try:
        socket.bind(bind_endpoint(run.server))
        bound = socket.getsockopt_string(zmq.LAST_ENDPOINT)
        logger.info("server listening on %s, waiting for %d agents", bound, run.agents.num_agents)
        if on_bound is not None:
            on_bound(bound)
        pool.wait_for_agents(run.server.register_timeout_s)
        if show_progress:  # timed from the first round on, not the wait for agents
            bar = Progress(run.rounds, "rounds", done=progress.next_round - 1)
            callbacks.append(_progress_callback(bar, has_goal=first.has_goal))
        from fedhpg.server.buffered_zmq import ZmqBufferedCoordinator  # the in-process loop

        kind = ZmqBufferedCoordinator if run.server.round_policy == "buffered" else Coordinator
        coordinator = kind(
            run=run,
            pool=pool,
            strategy=strategy,
            theta=theta,
            progress=progress,
            on_round=callbacks,
        )
        theta = coordinator.run_rounds()
        pool.shutdown("run complete")
    except BaseException as error:
        pool.shutdown(f"the server stopped: {error or type(error).__name__}", complete=False)
        raise
    finally:
        if bar is not None:
            bar.close()
        metrics.close()
        if board is not None:
            board.close()
        connections.stop()
        security.stop()  # the ZAP thread
        socket.close(linger=200)
        context.term()
    params = {
        agent: {"gamma": variant.gamma, **variant.params}
        for agent, variant in zip(pool.agent_ids, run_variants(run), strict=True)
    }
    summary = {
        "rounds": run.rounds,
        "final_eval_round": last_eval.get("round"),
        "eval": {a: e.to_json() for a, e in last_eval["eval"].items()} if last_eval else None,
        **pool.counters(),
        **connections.counts.as_dict(),
        "variants": params,
    }
    write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2).encode())
    if last_eval:
        # each agent's budget only for the table (~1 ms an agent where a population draws it)
        algorithm, _ = resolve_algorithm(run)
        compute = {}
        for k, agent in enumerate(pool.agent_ids):
            profile = agent_profile(run, k)
            compute[agent] = f"{algorithm.describe_budget(profile.budget)} speed={profile.speed:g}"
        sys.stdout.write(
            f"\nUnified policy after round {last_eval['round']} "
            f"({run.eval.episodes} {'greedy' if run.eval.greedy else 'sampled'} episodes "
            "per environment):\n"
            + evaluation_table(last_eval["eval"], params, compute, has_goal=first.has_goal)
            + "\n"
        )
    sys.stdout.write(f"run directory: {out_dir.resolve()}\n")
    sys.stdout.flush()
    return ServerResult(theta=theta, out_dir=out_dir, last_evaluation=last_eval.get("eval"))


def max_connections(run: RunConfig) -> int:
    """``server.max_connections``, or by default room for every agent twice over (a restarted
    agent's new connection while its old one closes) and 64 more."""
    configured = run.server.max_connections
    return configured if configured is not None else 2 * run.agents.num_agents + 64


def _main(run: RunConfig) -> int:
    out_dir = Path(run.server.out_dir) if run.server.out_dir else default_out_dir()
    if run.resume and run.resume.lower() != "true":
        out_dir = Path(run.resume)
    on_bound = None
    if run.server.endpoint_file:
        on_bound = endpoint_writer(run, Path(run.server.endpoint_file))
    try:
        serve(run, out_dir=out_dir, on_bound=on_bound)
    except (FederationError, RunDirectoryError) as error:
        logger.error("%s", error)
        return 1
    except zmq.ZMQError as error:
        sys.stderr.write(f"error: {bind_error(run, error)}\n")
        return 1
    return 0


def endpoint_writer(run: RunConfig, path: Path) -> Callable[[str], None]:
    """``server.endpoint_file``: once bound, where agents reach this server, as JSON
    (``host``, ``port``, ``transport``), written atomically so a reader never sees half of it.
    Bound to every interface, the advertised host is ``cluster.advertise_host`` or this node's
    name; otherwise the host it bound."""

    def write(bound: str) -> None:
        record: dict[str, Any] = {"transport": run.server.transport, "endpoint": bound}
        if run.server.transport == "tcp":
            host = run.server.host
            if run.server.bind_all:
                host = run.cluster.advertise_host or socket_module.gethostname()
            record |= {"host": host, "port": int(bound.rsplit(":", 1)[1])}
        try:
            write_atomic(path, json.dumps(record).encode())
        except OSError as error:
            raise RunDirectoryError(
                f"server.endpoint_file: cannot write {path}: {error.strerror or error}"
            ) from None

    return write


def bind_error(run: RunConfig, error: zmq.ZMQError) -> str:
    """One line for an endpoint the server cannot listen on (a port in use, a bad address):
    exit status 1, since the setting may be right and the machine's state is what fails."""
    key = "server.port" if run.server.transport == "tcp" else "server.ipc_path"
    return f"{key}: cannot listen on {bind_endpoint(run.server)}: {error.strerror or error}"


def main() -> None:
    sys.exit(run_entry(_main, resumable=True))
