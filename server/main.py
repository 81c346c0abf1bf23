"""``fedhpg-server``: bind, wait for the K agents, run the rounds, write the run directory."""

from __future__ import annotations

import json
import logging
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
from fedhpg.common.config import ConfigError, RunConfig, dictated_settings, groups, to_dict
from fedhpg.common.runtime.cli import run_entry
from fedhpg.common.runtime.progress import Progress
from fedhpg.common.types import EvaluationStats
from fedhpg.common.variants import run_variants, variant_digest
from fedhpg.common.wire.security import secure_server_socket
from fedhpg.common.wire.transport import bind_endpoint, configure_socket, max_message_bytes
from fedhpg.common.worker import initial_theta
from fedhpg.server.checkpoint import (
    Checkpoint,
    latest_valid_checkpoint,
    save_checkpoint,
    write_atomic,
)
from fedhpg.server.coordinator import Coordinator, RoundCallback, RoundRecord, RunProgress
from fedhpg.server.metrics import MetricsWriter
from fedhpg.server.pools import FederationError
from fedhpg.server.pools.zmq_pool import ZmqAgentPool
from fedhpg.server.report import evaluation_table
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


def _progress_callback(progress: Progress) -> Callable[[RoundRecord, torch.Tensor], None]:
    def update(record: RoundRecord, _: torch.Tensor) -> None:
        status = f"round {record.round_time_s:.2f}s"
        if record.eval:
            success = [e.success_rate for e in record.eval.values()]
            returns = [e.return_mean for e in record.eval.values()]
            mean_return = sum(returns) / len(returns)
            status += f" | eval success min {min(success):.2f}, mean return {mean_return:.3f}"
        progress.update(1, status)

    return update


def _checkpoint_callback(
    run: RunConfig, directory: Path, progress: RunProgress
) -> Callable[[RoundRecord, torch.Tensor], None]:
    settings = to_dict(run)

    def save(record: RoundRecord, theta: torch.Tensor) -> None:
        save_checkpoint(
            directory,
            Checkpoint(
                round=record.round,
                theta=theta,
                config=settings,
                metrics_lines=record.round,
                state={
                    "trajectories_per_agent": progress.trajectories_per_agent,
                    "elapsed_s": progress.elapsed_s,
                },
                strategy=progress.strategy_state,
            ),
        )

    return save


def resume_point(
    run: RunConfig, out_dir: Path, strategy: Strategy[Any]
) -> tuple[torch.Tensor, RunProgress]:
    """θ̃ and the run's progress from the newest valid checkpoint; metrics cut back to it."""
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    if checkpoint is None:
        raise ConfigError("resume", f"no valid checkpoint in {out_dir / 'checkpoints'}")
    current = to_dict(run)
    for key in groups("fixed"):
        if checkpoint.config.get(key) != current[key]:
            raise ConfigError(
                key, f"differs from the checkpointed run in {out_dir}; resume keeps it"
            )
    metrics = out_dir / "metrics.jsonl"
    if metrics.exists():
        kept = metrics.read_text(encoding="utf-8").splitlines()[: checkpoint.metrics_lines]
        write_atomic(metrics, "".join(line + "\n" for line in kept).encode())
    logger.warning("resuming %s after round %d", out_dir, checkpoint.round)
    if strategy.state().scalars and not checkpoint.strategy.scalars:
        raise ConfigError(
            "resume",
            f"the checkpoint holds no state of strategy {strategy.name!r}; it cannot be resumed",
        )
    progress = RunProgress(
        next_round=checkpoint.round + 1,
        trajectories_per_agent=float(checkpoint.state.get("trajectories_per_agent", 0.0)),
        elapsed_s=float(checkpoint.state.get("elapsed_s", 0.0)),
        strategy_state=checkpoint.strategy,
    )
    return checkpoint.theta, progress


def serve(
    run: RunConfig,
    *,
    out_dir: Path,
    on_bound: Callable[[str], None] | None = None,
    show_progress: bool = True,
) -> ServerResult:
    """Run one federation as its server; returns the final θ̃_T."""
    validate_strategy(run)
    strategy = make_strategy(run.strategy)
    out_dir.mkdir(parents=True, exist_ok=True)
    variants = run_variants(run)
    theta, progress = initial_theta(variants[0], run), RunProgress()
    if run.resume:
        theta, progress = resume_point(run, out_dir, strategy)
    (out_dir / "config.json").write_text(json.dumps(to_dict(run), indent=2))
    context = zmq.Context()
    socket = context.socket(zmq.ROUTER)
    configure_socket(socket, run.server)
    guard = secure_server_socket(socket, context, run.security)  # security: CURVE+ZAP, pre-bind
    socket.setsockopt(zmq.ROUTER_MANDATORY, 1)
    endpoint = bind_endpoint(run.server)
    socket.bind(endpoint)
    bound = socket.getsockopt_string(zmq.LAST_ENDPOINT)
    logger.info("server listening on %s, waiting for %d agents", bound, run.agents.num_agents)
    if on_bound is not None:
        on_bound(bound)
    pool = ZmqAgentPool(
        socket=socket,
        num_agents=run.agents.num_agents,
        check=UpdateCheck(
            num_params=int(theta.numel()), max_update_norm=run.server.max_update_norm
        ),
        env_signature=variants[0].signature(),
        variant_digests=[variant_digest(run, v) for v in variants],
        run_settings=dictated_settings(run),  # security: only dictated keys leave the server
        run_id=uuid.uuid4().hex[:12],
        max_bytes=max_message_bytes(run.server),
        settings=run.server,
    )
    metrics = MetricsWriter(out_dir / "metrics.jsonl")
    last_eval: dict[str, Any] = {}

    def keep_eval(record: RoundRecord, _: torch.Tensor) -> None:
        if record.eval:
            last_eval["round"], last_eval["eval"] = record.round, record.eval

    callbacks: list[RoundCallback] = [
        metrics,
        _checkpoint_callback(run, out_dir / "checkpoints", progress),
        keep_eval,
    ]
    if show_progress:
        bar = Progress(run.rounds, "rounds")
        bar.done = progress.next_round - 1
        callbacks.append(_progress_callback(bar))
    try:
        pool.wait_for_agents(run.server.register_timeout_s)
        coordinator = Coordinator(
            run=run,
            pool=pool,
            strategy=strategy,
            theta=theta,
            progress=progress,
            on_round=callbacks,
        )
        theta = coordinator.run_rounds()
        pool.shutdown("run complete")
    except BaseException:
        pool.shutdown("server stopped")
        raise
    finally:
        metrics.close()
        guard.stop()  # security: the ZAP thread and the handshake log
        socket.close(linger=200)
        context.term()
    params = {
        agent: {"gamma": variants[k].gamma, **variants[k].params}
        for k, agent in enumerate(pool.agent_ids)
    }
    algorithm, _ = resolve_algorithm(run)
    compute = {}
    for k, agent in enumerate(pool.agent_ids):
        profile = agent_profile(run, k)
        compute[agent] = f"{algorithm.describe_budget(profile.budget)} speed={profile.speed:g}"
    summary = {
        "rounds": run.rounds,
        "final_eval_round": last_eval.get("round"),
        "eval": {a: e.to_json() for a, e in last_eval["eval"].items()} if last_eval else None,
        "rejected_messages": pool.rejected,
        "late_answers": pool.late_answers,
        "agent_deaths": pool.deaths,
        "agent_rejoins": pool.rejoins,
        "variants": params,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    if last_eval:
        sys.stdout.write(
            f"\nUnified policy after round {last_eval['round']} "
            f"({run.eval.episodes} {'greedy' if run.eval.greedy else 'sampled'} episodes "
            "per environment):\n" + evaluation_table(last_eval["eval"], params, compute) + "\n"
        )
    sys.stdout.write(f"run directory: {out_dir.resolve()}\n")
    sys.stdout.flush()
    return ServerResult(theta=theta, out_dir=out_dir, last_evaluation=last_eval.get("eval"))


def _main(run: RunConfig) -> int:
    out_dir = Path(run.server.out_dir) if run.server.out_dir else default_out_dir()
    if run.resume and run.resume.lower() != "true":
        out_dir = Path(run.resume)
    try:
        serve(run, out_dir=out_dir)
    except FederationError as error:
        logger.error("%s", error)
        return 1
    except zmq.ZMQError as error:
        logger.error("cannot serve on %s: %s", bind_endpoint(run.server), error)
        return 1
    return 0


def main() -> None:
    sys.exit(run_entry(_main))
