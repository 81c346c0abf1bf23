"""The server of a distributed run: bind, wait for the K agents, run the rounds, write the run
directory (what ``fedhpg-server`` and the server that ``fedhpg-run`` forks do).

The run is checked and assembled by :mod:`fedhpg.server.assembly`; here is what only a server
with agent processes has: its ROUTER socket (CURVE and the ZAP handler when on, the
connection guard, the message cap that θ's size and hosts' batches need), the
:class:`~fedhpg.server.pools.zmq_pool.ZmqAgentPool` over it, the progress bar, and the final
table of the unified policy's evaluation.
"""

from __future__ import annotations

import logging
import sys
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import zmq

from fedhpg.common.configuration.config import RunConfig, attacking_agents
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.placement import agents_per_host
from fedhpg.common.configuration.run_roles import dictated_settings
from fedhpg.common.heterogeneity.variants import discount, run_variants, variant_digest, variant_of
from fedhpg.common.learning.components import agent_profile, resolve_algorithm
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.runtime.progress import Progress
from fedhpg.common.wire.codec import MAX_HEADER_BYTES
from fedhpg.common.wire.security import (
    ServerGuard,
    handshake_failure_logger,
    secure_server_socket,
)
from fedhpg.common.wire.transport import (
    batch_message_cap,
    bind_endpoint,
    configure_socket,
    max_message_bytes,
    single_message_bytes,
)
from fedhpg.server.assembly import Assembly, CheckedRun, assemble, check_run
from fedhpg.server.buffered_zmq import ZmqBufferedCoordinator
from fedhpg.server.connections import ConnectionGuard, connection_budget
from fedhpg.server.coordinator import RoundRecord
from fedhpg.server.pools.secure import SecureExchange, neighbour_count, row_bytes
from fedhpg.server.pools.zmq_pool import ZmqAgentPool
from fedhpg.server.report import evaluation_report
from fedhpg.server.run_dir import claimed
from fedhpg.server.validation import UpdateCheck

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ServerResult:
    theta: torch.Tensor
    out_dir: Path
    last_evaluation: dict[str, EvaluationStats] | None


def sleeps_to_emulate(run: RunConfig) -> bool:
    """Whether the run's agent processes sleep to emulate their devices: the sleeping clock
    (``agents.virtual_clock=false``), one agent per process (a host never sleeps), and some
    slowness to emulate (a speed below 1, a step delay, a latency, or a population that
    draws them)."""
    agents = run.agents
    if agents.virtual_clock or agents_per_host(run) > 1:
        return False
    drawn = agents.population.kind != "none" and bool(
        {"speed", "step_delay_s", "latency_s"} & set(agents.population.draw)
    )
    return (
        drawn
        or any(speed < 1 for speed in agents.speeds)
        or any(delay > 0 for delay in agents.step_delays_s)
        or any(latency > 0 for latency in agents.latencies_s)
    )


def message_cap(run: RunConfig, num_params: int) -> int:
    """The largest message this run's agents may send: a header and θ_k, or an agent host's
    batch of θs (ZMQ_MAXMSGSIZE and the codec's cap). ``server.max_message_mb`` may lower it
    only as far as one θ."""
    needed = single_message_bytes(num_params)
    if run.privacy.mode in ("secagg", "dp_secagg"):  # a secure round's rows, one at least
        needed = max(needed, MAX_HEADER_BYTES + 4096 + row_bytes(run, num_params))
    configured = max_message_bytes(run.server)
    if configured < needed:
        raise ConfigError(
            "server.max_message_mb",
            f"got {run.server.max_message_mb:g}, below the {needed / 2**20:.3g} MiB this run's "
            f"updates need (θ of {num_params} float32 and a header of up to 1 MiB)",
        )
    cap = batch_message_cap(configured, num_params)
    if needed > cap:
        raise ConfigError(
            "privacy.secagg.neighbours",
            f"one agent's secret shares for its {neighbour_count(run, run.agents.num_agents)} "
            f"neighbours take {needed / 2**20:.3g} MiB, more than a message of this run may "
            f"({cap / 2**20:.3g} MiB): set privacy.secagg.neighbours (e.g. 32)",
        )
    return cap


DIGESTS_SHOWN_FROM = 100_000
"""Agents from which the server shows its progress through their digests before it listens
(O(K): long enough at that size that a silent server would look hung)."""
DIGESTS_PER_UPDATE = 10_000


def run_digests(run: RunConfig) -> list[str]:
    """Every agent's :func:`variant_digest`, what the server checks each hello against. The
    variants are made a chunk at a time and dropped: K short strings stay (~1 MB at K=10 000).
    From :data:`DIGESTS_SHOWN_FROM` agents on, the work is shown as it goes."""
    count = run.agents.num_agents
    if count < DIGESTS_SHOWN_FROM:
        return [variant_digest(run, variant) for variant in run_variants(run)]
    logger.info(
        "computing the environment digests of %d agents before listening (each agent's "
        "registration is checked against its own): O(K)",
        count,
    )
    progress = Progress(count, "agents' digests")
    digests: list[str] = []
    for variant in run_variants(run):
        digests.append(variant_digest(run, variant))
        if len(digests) % DIGESTS_PER_UPDATE == 0 or len(digests) == count:
            progress.update(len(digests) - progress.done)
    progress.close()
    return digests


def max_connections(run: RunConfig) -> int:
    """``server.max_connections``, or by default room for every agent twice over (a restarted
    agent's new connection while its old one closes) and 64 more."""
    configured = run.server.max_connections
    return configured if configured is not None else 2 * run.agents.num_agents + 64


def bind_error(run: RunConfig, error: zmq.ZMQError) -> str:
    """One line for an endpoint the server cannot listen on (a port in use, a bad address):
    exit status 1, since the setting may be right and the machine's state is what fails."""
    reason = zmq.strerror(error.errno) if error.errno else str(error)
    if run.server.transport != "tcp":
        return f"server.ipc_path: cannot listen on {bind_endpoint(run.server)}: {reason}"
    where = f"{run.server.host}:{run.server.port}"
    hint = (
        " (choose another port; server.port=0 takes a free one)"
        if error.errno == zmq.EADDRINUSE
        else ""
    )
    return f"server.port: cannot listen on {where}: {reason}{hint}"


@dataclass
class ServerSocket:
    """The bound ROUTER socket's parts: its context, the connection guard, the ZAP thread."""

    context: zmq.Context
    socket: zmq.Socket
    guard: ConnectionGuard
    security: ServerGuard

    def close(self) -> None:
        self.guard.stop()
        self.security.stop()  # the ZAP thread
        self.socket.close(linger=200)
        self.context.term()


@contextmanager
def server_socket(run: RunConfig, cap: int) -> Iterator[ServerSocket]:
    """The ROUTER socket with every option set, not yet bound (closed at the block's end)."""
    context = zmq.Context()
    socket = context.socket(zmq.ROUTER)
    configure_socket(socket, run.server)
    socket.setsockopt(zmq.MAXMSGSIZE, cap)
    security = secure_server_socket(socket, context, run.security)  # CURVE+ZAP, pre-bind
    socket.setsockopt(zmq.ROUTER_MANDATORY, 1)
    guard = ConnectionGuard(
        socket,
        max_inflight_bytes=2 * cap + 64 * 1024,
        hello_timeout_s=run.server.hello_timeout_s,
        max_connections=connection_budget(max_connections(run)),
        on_handshake_failed=handshake_failure_logger(curve=run.security.curve),
    ).start()  # before bind: every connection is seen
    parts = ServerSocket(context=context, socket=socket, guard=guard, security=security)
    try:
        yield parts
    finally:
        parts.close()


def zmq_pool(assembly: Assembly, parts: ServerSocket, cap: int) -> ZmqAgentPool:
    """The K agents of ``assembly``'s run, reached through ``parts``' socket."""
    run, checked = assembly.run, assembly.checked
    pool = ZmqAgentPool(
        socket=parts.socket,
        num_agents=run.agents.num_agents,
        check=UpdateCheck(
            num_params=int(checked.initial_theta.numel()),
            max_update_norm=run.server.max_update_norm,
        ),
        env_signature=checked.first.signature(),  # builds an env: once, not per agent
        variant_digests=run_digests(run),
        run_settings=dictated_settings(run),  # security: only dictated keys leave the server
        run_id=uuid.uuid4().hex[:12],
        max_bytes=cap,
        settings=run.server,
        guard=parts.guard,
        secure=SecureExchange(run, int(checked.initial_theta.numel()))
        if checked.privacy is not None and checked.privacy.secure
        else None,
    )
    pool.restore_counters(assembly.counters)
    return pool


def serve(
    run: RunConfig,
    *,
    out_dir: Path,
    on_bound: Callable[[str], None] | None = None,
    show_progress: bool = True,
) -> ServerResult:
    """Run one federation as its server; returns the final θ̃_T. The socket is bound before
    the run directory is claimed: an address it cannot listen on leaves nothing behind."""
    checked = check_run(run, distributed=True)
    cap = message_cap(run, int(checked.initial_theta.numel()))
    with server_socket(run, cap) as parts:
        parts.socket.bind(bind_endpoint(run.server))
        bound = parts.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        with claimed(out_dir, resume=bool(run.resume)) as run_dir:
            assembly = assemble(checked, run_dir=run_dir)
            try:
                pool = zmq_pool(assembly, parts, cap)
                logger.info(
                    "server listening on %s, waiting for %d agents", bound, run.agents.num_agents
                )
                if sleeps_to_emulate(run):
                    logger.info(
                        "the agents sleep to emulate slower devices (agents.speeds, "
                        "agents.step_delays_s, agents.latencies_s): most of this run's time is "
                        "that sleep; agents.virtual_clock=true accounts the same emulated time "
                        "without sleeping (the same θ̃)"
                    )
                if on_bound is not None:
                    on_bound(bound)
                theta = _serve(assembly, pool, show_progress)
            finally:
                assembly.close()
            assembly.finish(pool.agent_ids, **parts.guard.counts.as_dict())
    _print_report(checked, assembly, pool.agent_ids, out_dir)
    return ServerResult(theta=theta, out_dir=out_dir, last_evaluation=assembly.last.eval)


def _serve(assembly: Assembly, pool: ZmqAgentPool, show_progress: bool) -> torch.Tensor:
    run = assembly.run
    bar: Progress | None = None
    try:
        pool.wait_for_agents(run.server.register_timeout_s)
        if show_progress:  # timed from the first round on, not the wait for agents
            bar = Progress(run.rounds, "rounds", done=assembly.progress.next_round - 1)
            assembly.sinks.append(_progress_callback(bar, has_goal=assembly.checked.first.has_goal))
        theta = assembly.run_rounds(pool, buffered=ZmqBufferedCoordinator)
        pool.shutdown("run complete")
        return theta
    except BaseException as error:
        pool.shutdown(f"the server stopped: {error or type(error).__name__}", complete=False)
        raise
    finally:
        if bar is not None:
            bar.close()


def round_status(
    round_time_s: float, evaluation: dict[str, EvaluationStats] | None, *, has_goal: bool
) -> str:
    """A round's line on the progress bar: its time, and its evaluation's worst success rate
    (with a goal) and mean return when it was evaluated."""
    status = f"round {round_time_s:.2f}s"
    if evaluation:
        success = [e.success_rate for e in evaluation.values()]
        returns = [e.return_mean for e in evaluation.values()]
        mean_return = sum(returns) / len(returns)
        status += " | eval "
        status += f"success min {min(success):.2f}, " if has_goal else ""
        status += f"mean return {mean_return:.3f}"
    return status


def _progress_callback(
    progress: Progress, *, has_goal: bool
) -> Callable[[RoundRecord, torch.Tensor], None]:
    def update(record: RoundRecord, _: torch.Tensor) -> None:
        progress.update(1, round_status(record.round_time_s, record.eval, has_goal=has_goal))

    return update


def _print_report(
    checked: CheckedRun, assembly: Assembly, agent_ids: list[str], out_dir: Path
) -> None:
    last = assembly.last
    print_report(
        checked.run,
        last_round=last.round,
        evaluation=last.eval,
        agent_ids=agent_ids,
        has_goal=checked.first.has_goal,
        out_dir=out_dir,
    )


def print_report(
    run: RunConfig,
    *,
    last_round: int | None,
    evaluation: dict[str, EvaluationStats] | None,
    agent_ids: list[str],
    has_goal: bool,
    out_dir: Path,
) -> None:
    """The unified policy's last evaluation (of round ``last_round``) per agent, then where the
    run directory is."""
    if evaluation:
        sys.stdout.write(
            f"\nUnified policy after round {last_round} "
            f"({run.eval.episodes} {'greedy' if run.eval.greedy else 'sampled'} episodes "
            "per environment):\n"
            + final_report(run, evaluation, agent_ids, has_goal=has_goal)
            + "\n"
        )
    sys.stdout.write(f"run directory: {out_dir.resolve()}\n")
    sys.stdout.flush()


def final_report(
    run: RunConfig,
    evaluation: dict[str, EvaluationStats],
    agent_ids: list[str],
    *,
    has_goal: bool,
) -> str:
    """The final table of ``evaluation`` (agent id → stats; ``agent_ids`` in index order): each
    row's compute budget and environment variant are made only for the rows shown (a
    population draws them, which is slow for many agents)."""
    index = {agent: k for k, agent in enumerate(agent_ids)}
    algorithm, _ = resolve_algorithm(run)

    def describe(agent: str) -> tuple[str, dict[str, Any]]:
        k = index[agent]
        profile = agent_profile(run, k)
        variant = variant_of(run, k)
        compute = f"{algorithm.describe_budget(profile.budget)} speed={profile.speed:g}"
        return compute, {"gamma": discount(run, variant), **variant.params}

    attackers = [agent_ids[k] for k in attacking_agents(run) if k < len(agent_ids)]
    return evaluation_report(
        evaluation, describe, has_goal=has_goal, attackers=attackers, attack=run.attack.kind
    )
