"""The ``server`` and ``checkpoint`` sections: transport, timeouts, round policy, buffered
rounds, checks on updates, and checkpoints (read by :mod:`fedhpg.server`).
"""

from __future__ import annotations

from dataclasses import dataclass

from fedhpg.common.configuration.settings.checks import (
    check_choice,
    check_int,
    check_number,
    require,
)
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES

TRANSPORTS = ("tcp", "ipc")
STALENESS_WEIGHTS = ("inverse_sqrt", "constant")

# Liveness, part of the protocol: a peer silent for HEARTBEAT_LIVENESS intervals is presumed
# dead. (Defaults of ServerConfig; fedhpg.common.wire.protocol re-exports them.)
HEARTBEAT_INTERVAL_S = 1.0
HEARTBEAT_LIVENESS = 5


@dataclass(kw_only=True)
class CheckpointConfig:
    """Which checkpoints the run directory keeps besides the rolling newest two."""

    keep_best: bool = False
    """Also keep the checkpoint of the best evaluation so far (mean return over the agents)
    as ``checkpoints/best.safetensors``; summary.json's ``best`` names its round and return."""
    every: int | None = None
    """Also keep every N-th round's checkpoint, never rotated away, in
    ``checkpoints/kept/``; None = only the rolling newest two."""


@dataclass(kw_only=True)
class ServerConfig:
    """Where the server listens and how long it waits."""

    host: str = "127.0.0.1"
    """Address to bind (server) and to connect to (agents). Loopback unless asked otherwise."""
    port: int = 5555
    """TCP port; 0 lets the launcher pick a free one."""
    transport: str = "tcp"
    """'tcp' or 'ipc' (a Unix socket at ``ipc_path``)."""
    ipc_path: str = "/tmp/fedhpg.sock"
    """Socket path for transport 'ipc'."""
    bind_all: bool = False
    """Bind every interface (0.0.0.0) instead of ``host``: for multi-host federations."""
    register_timeout_s: float = 60.0
    """How long the server waits for all K agents to register."""
    round_timeout_s: float = 600.0
    """Hard cap on one round (or evaluation): past it the run fails, naming who is missing."""
    round_policy: str = "wait_all"
    """'wait_all': Algorithm 1 as written, every agent's update, a dead agent is waited for
    until it rejoins (``rejoin_timeout_s``); 'deadline': aggregate the updates that arrived
    by ``round_deadline_s`` if at least ``min_agents`` did, the rest are stragglers;
    'buffered': asynchronous rounds (FedBuff-style), θ̃ is aggregated from every
    ``buffer_size`` arrivals, each agent restarting at once from the newest θ̃ (in process:
    in emulated-time order; with agent processes: in arrival order, one agent per process).
    """
    round_deadline_s: float = 60.0
    """'deadline' policy: seconds after the broadcast at which the round is aggregated (in
    process: emulated seconds, an update whose emulated time exceeds it is a straggler)."""
    min_agents: int = 1
    """'deadline' policy: fewest updates a round may be aggregated from."""
    rejoin_timeout_s: float = 120.0
    """'wait_all' policy: how long a dead agent may stay away before the run fails."""
    heartbeat_interval_s: float = HEARTBEAT_INTERVAL_S
    """Both sides send a heartbeat this often (when they have nothing else to say)."""
    heartbeat_liveness: int = HEARTBEAT_LIVENESS
    """A peer silent for this many heartbeat intervals is presumed dead."""
    max_update_norm: float | None = None
    """Reject an update whose distance ‖θ_k − θ̃‖ exceeds this (a failure for the round);
    None = no bound. NaN/Inf and wrong shapes are always rejected. Every pool applies it.
    Under secure aggregation (the server sees no θ_k) it bounds the round's average step
    instead: a round past it is skipped (some update was past it)."""
    max_failed_rounds: int = 3
    """Secure rounds that may be skipped in a row (too few keys, inputs or shares; too little
    noise; a sum no honest agents could send: θ̃ kept, the round recorded) before the run
    stops, its checkpoint intact."""
    max_message_mb: float = 256.0
    """Upper bound on a message, in MiB. The server accepts no more than its run needs (a
    1 MiB header and θ as float32: ZMQ_MAXMSGSIZE and the codec's cap) and refuses to start
    if this is lower than that."""
    max_connections: int | None = None
    """Most connections the server keeps open (the oldest unregistered ones are closed past
    it); None = 2 × agents.num_agents + 64, lowered to what the descriptor limit allows. With
    agent hosts only the hosts' connections count (set it as low as twice their number)."""
    hello_timeout_s: float = 10.0
    """A connection that has not registered within this time is closed."""
    out_dir: str | None = None
    """Run directory for metrics and checkpoints; None = a new runs/<date>-<time>-<env>-<algo>
    (every entry point names its run directories so)."""
    tensorboard: bool = True
    """Also write TensorBoard event files to ``<out_dir>/tensorboard/`` (needs the optional
    ``tensorboard`` package; without it a warning, and metrics.jsonl alone)."""
    tensorboard_agents: int = 100
    """Per-agent TensorBoard scalars (``agent/<k>/…``, ``eval/<id>/…``) for runs of at most
    this many agents; larger runs write the federation's and the across-agent keys only
    (metrics.jsonl keeps every agent)."""
    wandb: bool = False
    """Also log every round to Weights & Biases (needs the optional ``wandb`` package: pip
    install 'fedhpg[wandb]'); its files go to ``<out_dir>/wandb/``, and ``WANDB_MODE=offline``
    keeps them there, to sync later."""
    wandb_project: str = "fedhpg"
    """The W&B project of the run (``server.wandb``); the run is named after its directory."""
    endpoint_file: str | None = None
    """Once listening, write where agents reach the server to this JSON file (host, port):
    how ``fedhpg-cluster``'s agent jobs find a server on a port it chose (shared filesystem)."""
    buffer_size: int | None = None
    """'buffered' policy: M, the arrivals aggregated into each new θ̃, in [1, agents.num_agents];
    None = agents.num_agents (with every agent in the buffer: synchronous rounds)."""
    max_staleness: int | None = None
    """'buffered' policy: an update started from a θ̃ more than this many versions old is
    dropped (recorded under ``stale``) and its agent restarts from the newest θ̃; None = no
    bound."""
    staleness_weight: str = "inverse_sqrt"
    """'buffered' policy: the weight of an update of staleness s in its buffer's mean change,
    'inverse_sqrt' (FedBuff's 1/sqrt(1 + s)) or 'constant' (1)."""
    diverged_share: float = 0.5
    """'buffered' policy: the run stops (diverged) once more than this share of the K agents
    had an update rejected since the last θ̃. Distinct agents count: an agent whose update is
    rejected waits for the next θ̃, so one peer that keeps failing never ends a run."""


def validate_server(server: ServerConfig, num_agents: int) -> None:
    check_int(server.port, "server.port", low=0)
    require(server.port <= 65535, "server.port", f"got {server.port!r}, must be <= 65535")
    check_choice(server.transport, "server.transport", TRANSPORTS)
    for key in (
        "register_timeout_s",
        "round_timeout_s",
        "round_deadline_s",
        "rejoin_timeout_s",
        "heartbeat_interval_s",
        "max_message_mb",
        "hello_timeout_s",
    ):
        check_number(getattr(server, key), f"server.{key}", low=0.0, low_open=True)
    check_choice(server.round_policy, "server.round_policy", ROUND_POLICIES)
    check_int(server.min_agents, "server.min_agents", low=1)
    require(
        server.min_agents <= num_agents,
        "server.min_agents",
        f"got {server.min_agents}, must be <= agents.num_agents={num_agents}",
    )
    validate_buffered(server, num_agents)
    check_int(server.heartbeat_liveness, "server.heartbeat_liveness", low=2)
    if server.max_update_norm is not None:
        check_number(server.max_update_norm, "server.max_update_norm", low=0.0, low_open=True)
    check_int(server.max_failed_rounds, "server.max_failed_rounds", low=0)
    if server.max_connections is not None:
        # low=1, not K: agent hosts serve many agents over one connection each
        check_int(server.max_connections, "server.max_connections", low=1)
    check_int(server.tensorboard_agents, "server.tensorboard_agents", low=0)


def validate_buffered(server: ServerConfig, num_agents: int) -> None:
    if server.buffer_size is not None:
        check_int(server.buffer_size, "server.buffer_size", low=1)
        require(
            server.buffer_size <= num_agents,
            "server.buffer_size",
            f"got {server.buffer_size}, must be <= agents.num_agents={num_agents}",
        )
    if server.max_staleness is not None:
        check_int(server.max_staleness, "server.max_staleness", low=0)
    check_choice(server.staleness_weight, "server.staleness_weight", STALENESS_WEIGHTS)
    check_number(server.diverged_share, "server.diverged_share", low=0.0, low_open=True)
    require(
        server.diverged_share <= 1.0,
        "server.diverged_share",
        f"got {server.diverged_share!r}, must be in (0, 1]",
    )
