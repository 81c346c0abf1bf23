"""Typed run configuration, validated once at the entry points.

The dataclasses double as Hydra structured configs (see ``fedhpg.conf``). Inner code receives
these objects, never a DictConfig. :func:`validate` raises :class:`ConfigError` naming the key
and the allowed values; entry points turn it into a one-line message and exit status 2.

This module is pure Python (no torch, zmq or gymnasium): every process imports it first, and
the checks that need a registry (algorithm, strategy, their options) live beside the registry
(:mod:`fedhpg.common.components`, :mod:`fedhpg.server.strategies`).

:data:`GROUPS` is the one declaration of what each top-level key is for: whether the server
dictates it to agents, whether a resumed run must keep it, whether runs that differ in it are
different experiments (plots group by it).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.config_error import ConfigError
from fedhpg.common.limits import MAX_HOST_AGENTS
from fedhpg.common.registry import Registry, import_plugins
from fedhpg.common.vocabularies import ATTACKS, BASELINES, CLOCKS, ESTIMATORS, ROUND_POLICIES

REWARD_TO_GO: tuple[str, ...] = ("from_start", "from_step")
NORMALIZE: tuple[str, ...] = ("none", "batch", "episode")
OPTIMIZERS = ("sgd", "adam")
ENGINES = ("auto", "torch")
ENV_PATHS = ("auto", "gymnasium")
DEVICE_PATTERN = re.compile(r"cpu|cuda(:\d+)?")
"""``algo.device``: a torch device name the torch engine accepts."""
SCHEDULES = ("constant", "periodic", "random_walk")
PLANS = ("none", "theorem1")
TRANSPORTS = ("tcp", "ipc")
STALENESS_WEIGHTS = ("inverse_sqrt", "constant")
PARTICIPATION_MODES = ("all", "uniform", "trace")
TOLERANCE_CHECKS = ("refuse", "warn")
CLUSTER_KINDS = ("auto", "slurm", "local", "ray")
PRIVACY_MODES = ("none", "dp", "secagg", "dp_secagg")
BUDGET_PARTIES = ("model", "server")
LOG_STDS = ("state_independent", "state_dependent")

# Liveness, part of the protocol: a peer silent for HEARTBEAT_LIVENESS intervals is presumed
# dead. (Defaults of ServerConfig; fedhpg.common.wire.protocol re-exports them.)
HEARTBEAT_INTERVAL_S = 1.0
HEARTBEAT_LIVENESS = 5


GYM_FAMILY = "gym"
"""The family of any registered gymnasium id (``env.id``), varied by ``env.vary``."""


@dataclass(kw_only=True)
class EnvConfig:
    """Which environment family, and how its K variants differ."""

    family: str = "gridworld"
    """Environment family (see ``fedhpg.envs.registry.FAMILIES``)."""
    level: float = 0.5
    """Heterogeneity level in [0, 1]: 0 = identical variants, 1 = most different."""
    seed: int | None = None
    """Seed of the variant generator; None uses the run seed."""
    horizon: int | None = None
    """Trajectory horizon H; None uses the family's episode step limit."""
    gamma: float | None = None
    """One discount for every agent; None keeps each variant's own γ_k."""
    options: dict[str, Any] = field(default_factory=dict)
    """Family-specific generator options (e.g. GridWorld ``size``, ``vary_goal``)."""
    id: str | None = None
    """``env.family=gym`` (``env=gym``): the registered gymnasium id every agent runs, e.g.
    MountainCar-v0."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """``env=gym``: constructor keywords of every agent's environment (``gym.make(id,
    **kwargs)``)."""
    vary: dict[str, Any] = field(default_factory=dict)
    """``env=gym``: what differs between agents, name → a seeded distribution ({choice: [...]},
    {uniform: {low, high}}, {lognormal: {median, sigma}}) or {spread: s} (the environment's own
    value × (1 + s·level·u), u ~ U(−1, 1)); a constructor keyword, an attribute of the
    unwrapped environment, or ``gamma`` (the agent's discount)."""


@dataclass(kw_only=True)
class AlgoConfig:
    """The federated algorithm (agent side) and the local policy-gradient settings it uses."""

    name: str = "fedhpg"
    """A registered algorithm: 'fedhpg' (Algorithm 1), 'fedhpgvr' (Algorithm 2), or a plugin's."""
    estimator: str = "gpomdp"
    """'reinforce' (eq. 5) or 'gpomdp' (eq. 6)."""
    baseline: str = "mean"
    """'none' or 'mean' (leave-one-out batch mean: C_b for REINFORCE, C_bh for GPOMDP)."""
    step_size: float = 1.0
    """Step size η of the local gradient ascent."""
    optimizer: str = "sgd"
    """'sgd' (plain ascent, as in the paper) or 'adam' (state reset every round)."""
    grad_clip: float | None = None
    """Clip each local gradient estimate to this norm; None = off (the default). Biased for
    ∇J: a clipped estimate's mean is not the gradient (about 6 % off with the clip at 2‖∇J‖,
    40 % at ‖∇J‖ on a small tabular MDP); Assumption 3 bounds the gradient, it does not ask
    for a clip (docs/configuration.md, Estimator options)."""
    params: dict[str, Any] = field(default_factory=dict)
    """The algorithm's own options (its ``Params`` dataclass), e.g. FedHPGVR's ``iw_mode``."""
    engine: str = "auto"
    """Which backend supplies the engine's primitives (``common/engine``: every algorithm's
    one loop runs on either). 'torch': all of the process's agents sampled and differentiated
    together in torch on ``algo.device``, for every policy and family; 'auto': the same,
    except that honest agents with the MLP categorical policy on CartPole on the CPU are
    sampled and differentiated by the compiled numba backend (``common/batched``, several
    times faster there). The two round floats differently, so the server dictates the
    choice; within either an agent's θ does not depend on where it runs or with whom."""
    device: str = "cpu"
    """The torch device of the engine: 'cpu', 'cuda' or 'cuda:N'."""
    envs: str = "auto"
    """Where the torch engine's environments step: 'auto' in torch on ``algo.device`` for the
    families with a torch implementation (cartpole, acrobot, pendulum, mountaincar,
    gridworld: ``envs/device/``), through gymnasium on the CPU for the others; 'gymnasium'
    through gymnasium for every family (the reference the torch families are checked
    against). Their floats differ (float32 against gymnasium's float64), so the server
    dictates it."""
    memory_gib: float | None = None
    """What one process's engine may hold at once on ``algo.device``, in GiB: a round of more
    agents than fit is trained in chunks of agents, one after another (θ does not depend on
    it). None: 80% of the free memory of a CUDA device, 2 GiB on the CPU
    (``common/engine/memory.py``, docs/gpu.md)."""
    bound_estimates: bool = False
    """Estimate Theorem 1's constants every round (``common/bounds.py``): each agent's σ̂², M̂
    and ‖∇J_k‖² at θ̃ from the per-trajectory gradients of its first local batch, written as
    ``bound_variance``, ``bound_second_moment`` and ``bound_grad_norm_sq`` in its ``algorithm``
    statistics, and with τ_k ≥ 2 ``bound_smoothness`` (L̂, the secant between its first two
    iterations' gradients). About two more gradients per round; θ̃ is the same either way.
    FedHPG only."""
    reward_to_go: str = "from_start"
    """GPOMDP's reward-to-go: 'from_start' (eq. 6, Σ_{h≥t} γ^h r_h; unbiased) or 'from_step'
    (Σ_{h≥t} γ^{h−t} r_h, common practice: a departure from eq. 6, biased for ∇J;
    docs/configuration.md, Estimator options). 'from_step' needs estimator 'gpomdp'; FedHPGVR
    takes 'from_start' only."""
    normalize: str = "none"
    """Standardise the estimator's coefficients, (c − mean)/std over alive steps: 'none' (eq.
    5/6; unbiased), 'batch' (over the whole batch) or 'episode' (within each trajectory; GPOMDP
    only). Both are departures from eq. 5/6, biased for ∇J (docs/configuration.md, Estimator
    options); FedHPGVR takes 'none' only."""


# --- participation: who trains each round (server/participation.py applies it) ---------------


@dataclass(kw_only=True)
class ParticipationConfig:
    """Which agents are asked to train each round, before the strategy's own ``select``.

    Under ``strategy`` because it is the server's alone (agents never see it), a resumed run
    must keep it, and runs that differ in it are different experiments: the strategy group's
    roles exactly."""

    mode: str = "all"
    """'all' (the paper: every agent, every round), 'uniform' (``per_round`` agents drawn
    uniformly without replacement, from (seed, round) alone), 'trace' (the agents that the
    ``trace`` file does not mark offline in that round)."""
    per_round: int | None = None
    """'uniform': C, agents per round, in [1, agents.num_agents]."""
    trace: str | None = None
    """'trace': a CSV file ``agent,offline_from,offline_to`` (one offline interval of rounds,
    inclusive, per row; format in docs/strategies.md, Participation)."""


def _validate_tolerance(strategy: StrategyConfig, num_agents: int) -> None:
    if strategy.tolerate is not None:
        _check_int(strategy.tolerate, "strategy.tolerate", low=0)
        _require(
            strategy.tolerate < num_agents,
            "strategy.tolerate",
            f"got {strategy.tolerate}, must be < agents.num_agents={num_agents}",
        )
    _check_choice(strategy.tolerance_check, "strategy.tolerance_check", TOLERANCE_CHECKS)
    _require(
        isinstance(strategy.device, str) and DEVICE_PATTERN.fullmatch(strategy.device) is not None,
        "strategy.device",
        f"got {strategy.device!r}, allowed: cpu, cuda, cuda:N",
    )


def _validate_participation(participation: ParticipationConfig, num_agents: int) -> None:
    key = "strategy.participation"
    _check_choice(participation.mode, f"{key}.mode", PARTICIPATION_MODES)
    if participation.mode == "uniform":
        _require(
            participation.per_round is not None,
            f"{key}.per_round",
            "mode 'uniform' needs per_round, the number of agents asked each round",
        )
        _check_int(participation.per_round, f"{key}.per_round", low=1)
        _require(
            participation.per_round <= num_agents,  # type: ignore[operator]
            f"{key}.per_round",
            f"got {participation.per_round}, must be <= agents.num_agents={num_agents}",
        )
    if participation.mode == "trace":
        _require(
            isinstance(participation.trace, str) and bool(participation.trace.strip()),
            f"{key}.trace",
            "mode 'trace' needs trace, the path of an availability CSV",
        )
    # A setting its mode ignores would be silently ignored: say which mode takes it.
    for name, mode in (("trace", "trace"), ("per_round", "uniform")):
        value = getattr(participation, name)
        _require(
            value is None or participation.mode == mode,
            f"{key}.{name}",
            f"got {value!r}, which mode {participation.mode!r} does not use: add {key}.mode={mode}",
        )


@dataclass(kw_only=True)
class StrategyConfig:
    """How the server turns the round's updates into θ̃ (its ``select`` and ``aggregate``)."""

    name: str = "mean"
    """A registered strategy: mean, weighted, fedadam, median, trimmed_mean, or a plugin's."""
    params: dict[str, Any] = field(default_factory=dict)
    """The strategy's own options (its ``Params`` dataclass), e.g. fedadam's ``step_size``."""
    participation: ParticipationConfig = field(default_factory=ParticipationConfig)
    """Who trains each round (default: every agent, as in the paper)."""
    tolerate: int | None = None
    """A robust rule (median, trimmed_mean, fedadam over one): how many arbitrary updates
    every aggregated set must survive; None = the agents ``attack.agents`` lists (at least 1).
    Checked at start against the smallest set the run aggregates (``per_round`` agents with
    sampling, ``server.min_agents`` under a deadline)."""
    tolerance_check: str = "refuse"
    """What a run whose robust rule tolerates fewer than ``tolerate`` in its smallest set
    does: 'refuse' to start (one line) or 'warn' and run."""
    device: str = "cpu"
    """Where the rules of the θ_k (mean, weighted, median, trimmed_mean) compute on the round's
    [K, d] matrix of updates: 'cpu', or 'cuda'/'cuda:N' for a server whose K·d is large
    (the matrix crosses once, θ̃ comes back)."""


@dataclass(kw_only=True)
class PopulationConfig:
    """Per-agent budgets and device profiles drawn from seeded distributions or read from a
    trace file, resolved lazily per agent index (never a K-long list): see
    :mod:`fedhpg.common.population` and docs/configuration.md, "Populations"."""

    kind: str = "none"
    """'none' (the per-agent lists alone), 'drawn' (``draw``: one seeded distribution per
    field) or 'trace' (``trace``: a CSV, one row per agent). A field the population sets
    overrides its list; a field it leaves keeps the list."""
    draw: dict[str, Any] = field(default_factory=dict)
    """'drawn': field → distribution, e.g. ``batch_size: {choice: [8, 16], weights: [3, 1]}``,
    ``speed: {lognormal: {median: 1, sigma: 0.5}, min: 0.1, max: 4}`` or ``{uniform: {low:
    0, high: 1e-3}}``; agent k's value depends only on (seed, k, field)."""
    trace: str | None = None
    """'trace': a CSV path (absolute or relative to the working directory; every host needs
    it); header ``agent,<field>,...``, row i is agent i; agent k takes row k mod rows."""


@dataclass(kw_only=True)
class AgentsConfig:
    """Per-agent compute. A one-element list applies to every agent."""

    num_agents: int = 4
    """K, the number of agents."""
    budget: dict[str, list[Any]] = field(default_factory=dict)
    """Per-agent compute budget, keyed by the algorithm's ``Budget`` fields (FedHPG:
    ``batch_size`` B_k and ``local_iters`` τ_k; FedHPGVR: ``batch_size``, ``inner_steps`` N,
    ``mini_batch_size`` b_k); a missing key takes the algorithm's default."""
    speeds: list[float] = field(default_factory=lambda: [1.0])
    """Emulated device speed: a local iteration takes 1/speed of its real compute time."""
    step_delays_s: list[float] = field(default_factory=lambda: [0.0])
    """Emulated cost of one environment step (env-step throttle), in seconds."""
    latencies_s: list[float] = field(default_factory=lambda: [0.0])
    """Emulated one-way network latency per message, in seconds."""
    schedule: str = "constant"
    """Time variation of the speed: 'constant', 'periodic' or 'random_walk'."""
    schedule_period_rounds: int = 10
    """'periodic': period of the speed oscillation, in rounds."""
    schedule_amplitude: float = 0.5
    """'periodic' / 'random_walk': relative amplitude (speed × (1 ± amplitude))."""
    virtual_clock: bool = False
    """Account emulated time without sleeping (fast, reproducible heterogeneity studies)."""
    # The counted clock: emulated time priced from the work counted.
    clock: str = "measured"
    """'measured': emulated compute = thread CPU time measured here / speed (follows this
    machine's load); 'counted': priced from counted env steps, gradient steps and message
    bytes with the costs below, identical bit for bit on any machine."""
    step_costs_s: list[float] = field(default_factory=lambda: [1.2e-5])
    """Counted clock: seconds of one env step at speed 1 (sampling + the policy's forward)."""
    grad_costs_s: list[float] = field(default_factory=lambda: [1.1e-5])
    """Counted clock: seconds of one trajectory step's backward pass per 1e4 parameters."""
    bandwidths_mbps: list[float] = field(default_factory=lambda: [100.0])
    """Counted clock: link bandwidth in Mbit/s (0 = unlimited); message bytes are charged."""
    population: PopulationConfig = field(default_factory=PopulationConfig)
    """Budgets and device profiles per agent index from a distribution or a trace file."""
    per_host: int | str = "auto"
    """``fedhpg-run``: logical agents per agent process. 'auto': one process per agent up to
    32 agents (or as many as this machine has cores), else one agent host per core; always
    one per agent with buffered rounds. 1 = one process per agent; N > 1 = ceil(K/N) agent
    hosts, each serving N consecutive indices over one connection."""
    # Re-planning budgets during a run from Theorem 1: the server sends them.
    plan: str = "none"
    """'none': every agent trains with its configured budget; 'theorem1': the first
    ``plan_every`` rounds use the configured budgets, then every ``plan_every`` rounds the
    server re-chooses each agent's B_k, τ_k minimising eq. 7 over the rounds left, each round
    within ``plan_round_s``, from the speeds and bound estimates observed since the last plan
    (fedhpg only; needs algo.bound_estimates=true)."""
    plan_every: int = 10
    """'theorem1': P, the rounds between plans (each plan uses the last P rounds' records)."""
    plan_round_s: float = 0.0
    """'theorem1': emulated seconds a round may take (as long as its slowest agent); 0 = the
    slowest round of the first ``plan_every`` rounds (the configured budgets' pace)."""
    plan_max_return: float | None = None
    """'theorem1': J(θ*) assumed for the gap J(θ*) − J(θ̃_0) (null = the training horizon,
    the most a reward-1-per-step task returns); J(θ̃_0) is round 1's mean training return."""
    plan_batch_max: int = 64
    """'theorem1': largest B_k a plan may give (the smallest is 2)."""
    plan_local_iters_max: int = 8
    """'theorem1': largest τ_k a plan may give."""


@dataclass(kw_only=True)
class AttackConfig:
    """Byzantine agents, for robustness experiments only (off by default).

    The attacks FedPG-BR evaluates, applied by the attacking agents themselves: the server is
    never told who attacks.
    """

    kind: str = "none"
    """'none', 'zero_gradient' (send θ̃ back), 'random_noise' (add uniform noise of
    ``noise_scale`` × the update's range), 'sign_flip' (send −``sign_flip_scale`` × the
    update), 'reward_flip' (learn from negated rewards), 'random_action' (act uniformly at
    random while sampling)."""
    agents: list[int] = field(default_factory=list)
    """Indices of the attacking agents."""
    sign_flip_scale: float = 2.5
    """'sign_flip': the update sent is −scale × the honest one (FedPG-BR: 2.5)."""
    noise_scale: float = 3.0
    """'random_noise': noise U(−1, 1) × scale × (max − min of the honest update) (FedPG-BR: 3)."""


@dataclass(kw_only=True)
class PolicyConfig:
    """How to build the policy network for the run's spaces."""

    name: str = "auto"
    """'auto' (the built-in policy that fits the spaces: tabular, a CNN for images, else the
    MLP the actions take), a registered name ('tabular', 'mlp_categorical', 'gaussian_mlp',
    'mlp_multi_categorical', 'mlp_multi_binary', 'cnn', a plugin's), or a dotted path
    'package.module:Class' to a fedhpg Policy subclass."""
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    """Hidden layer widths of the MLP policies and of the CNN's head (ignored by the tabular
    policy)."""
    log_std: str = "state_independent"
    """Gaussian policies: 'state_independent' or 'state_dependent' log σ."""
    init_log_std: float = -0.5
    """Gaussian policies: initial log σ."""


@dataclass(kw_only=True)
class EvalConfig:
    """How the unified policy is evaluated in every agent's environment."""

    every: int = 5
    """Evaluate every E rounds (and after the last round)."""
    episodes: int = 20
    """Episodes per environment."""
    greedy: bool = True
    """Greedy (argmax / mean action) evaluation; False samples from the policy."""
    horizon: int | None = None
    """Episode step limit when evaluating; None = the training horizon (``env.horizon``).
    FedPG-BR trains HalfCheetah with H=500 but validates over up to 1000 steps."""
    stop_at: float | None = None
    """Stop the run after an evaluation whose mean return over the agents reaches this target
    (a complete run: summary.json's ``stopped_early`` names the round); None = run every
    round."""


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


@dataclass(kw_only=True)
class AgentConfig:
    """Who this agent process is."""

    index: int = 0
    """Agent index k: selects the environment variant and the compute profile."""
    id: str | None = None
    """Agent id on the wire; None = 'agent-<index>'. For an agent host: the host's id
    (None = 'host-<first>-<last>'); its logical agents are always 'agent-<k>'."""
    first: int | None = None
    """Set: this process is an agent host serving the logical agents first .. first+count-1
    over one connection (``agent.index`` is then unused); None: one agent, ``agent.index``."""
    count: int = 1
    """Agent host: how many consecutive logical agents it serves, from ``agent.first``."""
    connect_timeout_s: float = 60.0
    """Give up if the server has not answered within this time (at start, or after it fell
    silent)."""
    max_restarts: int = 2
    """``fedhpg-run``: restart a crashed agent process up to this many times (it rejoins at
    the current round and redoes the lost work exactly); one more crash stops the run."""


@dataclass(kw_only=True)
class SecurityConfig:
    """CURVE encryption and agent authentication. Off by default: plaintext on the wire."""

    curve: bool = False
    """Encrypt every connection with CURVE and admit only agents whose public key is allowed."""
    keys_dir: str | None = None
    """Directory written by ``fedhpg-keys``: the default location of every key file below."""
    server_secret_key: str | None = None
    """Server: its secret key file; None = ``<keys_dir>/server.key_secret``."""
    allowed_keys_dir: str | None = None
    """Server: directory of allowed agent public keys, one ``<agent id>.key`` file per agent;
    None = ``<keys_dir>/allowed``."""
    server_public_key: str | None = None
    """Agent: the server's public key file; None = ``<keys_dir>/server.key``."""
    agent_secret_key: str | None = None
    """Agent: its own secret key file; None = ``<keys_dir>/<agent id>.key_secret``."""
    signing_key: str | None = None
    """Agent, secure aggregation: its secret signing key file; None =
    ``<keys_dir>/<agent id>.sign_secret``. Needed wherever a roster is."""
    signers_dir: str | None = None
    """Agent, secure aggregation: the roster of every agent's public signing key; None =
    ``<keys_dir>/signers`` where it exists. Without one, key advertisements are not signed and
    the server is trusted to relay keys unchanged."""


@dataclass(kw_only=True)
class SecAggConfig:
    """Secure aggregation: agents mask their encoded updates so that the server learns only
    the sum (docs/privacy.md)."""

    corruption: float = 0.1
    """γ: the fraction of a round's agents that may collude with the server (which may also
    deviate from the protocol) without exposing any other agent's input: the round's graph
    and threshold are derived from it (docs/privacy.md)."""
    dropout: float = 0.1
    """δ: the fraction of a round's agents that may stop answering (besides the colluders)
    with the round still completing."""
    threshold: float | None = None
    """t = ⌊threshold · k⌋ + 1 of an agent's k neighbours rebuild its secrets; None = the
    smallest t that meets ``corruption`` and ``dropout``. A value that does not meet them is
    refused, saying which would."""
    neighbours: int | None = None
    """k, the agents each one masks with and shares its secrets with (SecAgg+); None = every
    other agent up to 64 a round, beyond that the fewest that meet ``corruption`` and
    ``dropout``. Cost per agent grows with k, not with the round."""
    range: float = 1.0e4
    """Each coordinate of an update is clipped to [−range, range] before its fixed-point
    encoding (resolution about n · range / 2⁶², n the round's agents)."""


@dataclass(kw_only=True)
class PrivacyConfig:
    """Agent-level differential privacy and secure aggregation (docs/privacy.md)."""

    mode: str = "none"
    """'none'; 'dp' (each update clipped, Gaussian noise added by the server, ε accounted);
    'secagg' (the server sees only the sum of masked updates); 'dp_secagg' (both: each agent
    adds its share of the noise to its clipped update before masking)."""
    epsilon: float | None = None
    """The run's budget ε: without ``noise_multiplier``, σ is chosen so that ``rounds`` rounds
    spend exactly this; with it, the run stops before a round would exceed it. Which party's ε
    it caps: ``budget_against``."""
    budget_against: str = "model"
    """'model': ``epsilon`` caps ε against readers of the released model (and, with 'dp', of
    the run directory); 'server': with 'dp_secagg', it caps ε against the server, which picks
    and sees each round's sample (no amplification by sampling; σ calibrated as if one agent
    took part in every round)."""
    delta: float | None = None
    """δ of the guarantee; None = min(1/(10·K), 10⁻⁵) (K = agents.num_agents)."""
    noise_multiplier: float | None = None
    """σ: the noise's std over the clip C; None = calibrated from ``epsilon``."""
    clip: float = 1.0
    """C, the L2 bound of each agent's update θ_k − θ̃ (the first round's, with adaptive
    clipping)."""
    adaptive_clip: bool = False
    """Follow a quantile of the update norms (Andrew et al. 2021) instead of a fixed C."""
    target_quantile: float = 0.5
    """Adaptive clipping: the fraction of updates C should leave unclipped."""
    clip_rate: float = 0.2
    """Adaptive clipping: the geometric step η of C ← C·exp(−η(b̄ − quantile))."""
    count_std: float | None = None
    """Adaptive clipping: std of the noise on the count of unclipped updates (above σ/2);
    None = the expected agents per round / 20, or σ where that is more."""
    noise_seed: int | None = None
    """Seed the DP noise, and the sample of a sampled DP run (reproducible experiments only:
    whoever knows it can remove the noise and knows the sample, so it protects nothing);
    None = the operating system's entropy."""
    secure_noise: bool | None = None
    """Unseeded DP noise from the operating system's CSPRNG, each draw a sum of four Gaussians
    (the floating-point mitigation of Opacus's secure mode); false: numpy's PCG64 seeded from
    the operating system. None = on unless ``noise_seed`` is set."""
    secagg: SecAggConfig = field(default_factory=SecAggConfig)
    """Secure aggregation's settings ('secagg', 'dp_secagg')."""

    @property
    def secure_noise_on(self) -> bool:
        """Whether unseeded noise is drawn as :class:`~fedhpg.common.privacy.dp.SecureNoise`."""
        return self.secure_noise if self.secure_noise is not None else self.noise_seed is None


def _validate_privacy(privacy: PrivacyConfig) -> None:
    _check_choice(privacy.mode, "privacy.mode", PRIVACY_MODES)
    if privacy.epsilon is not None:
        _check_number(privacy.epsilon, "privacy.epsilon", low=0.0, low_open=True)
    if privacy.delta is not None:
        _check_number(privacy.delta, "privacy.delta", low=0.0, low_open=True)
        _require(privacy.delta < 1, "privacy.delta", f"got {privacy.delta!r}, must be in (0, 1)")
    if privacy.noise_multiplier is not None:
        _check_number(privacy.noise_multiplier, "privacy.noise_multiplier", low=0.0, low_open=True)
    if privacy.mode in ("dp", "dp_secagg"):
        _require(
            privacy.epsilon is not None or privacy.noise_multiplier is not None,
            "privacy.epsilon",
            f"privacy.mode={privacy.mode} needs a budget ε (privacy.epsilon) or a noise "
            "multiplier (privacy.noise_multiplier)",
        )
    _check_number(privacy.clip, "privacy.clip", low=0.0, low_open=True)
    _require(
        isinstance(privacy.adaptive_clip, bool),
        "privacy.adaptive_clip",
        f"got {privacy.adaptive_clip!r}, must be true or false",
    )
    _check_number(privacy.target_quantile, "privacy.target_quantile", low=0.0)
    _require(
        privacy.target_quantile <= 1,
        "privacy.target_quantile",
        f"got {privacy.target_quantile!r}, must be in [0, 1]",
    )
    _check_number(privacy.clip_rate, "privacy.clip_rate", low=0.0, low_open=True)
    if privacy.count_std is not None:
        _check_number(privacy.count_std, "privacy.count_std", low=0.0, low_open=True)
    if privacy.noise_seed is not None:
        _check_int(privacy.noise_seed, "privacy.noise_seed", low=0)
    _require(
        not (privacy.secure_noise and privacy.noise_seed is not None),
        "privacy.secure_noise",
        f"got true with privacy.noise_seed={privacy.noise_seed}: seeded noise is numpy's, "
        "reproducible and known to whoever knows the seed; drop one of them",
    )
    _check_choice(privacy.budget_against, "privacy.budget_against", BUDGET_PARTIES)
    _require(
        privacy.budget_against == "model" or privacy.mode == "dp_secagg",
        "privacy.budget_against",
        f"got 'server' with privacy.mode={privacy.mode}: only dp_secagg's noise holds against "
        "the server (with 'dp' it is trusted: it sees every update); use 'model', or "
        "privacy=dp_secagg",
    )
    secagg = privacy.secagg
    if secagg.threshold is not None:
        _check_number(secagg.threshold, "privacy.secagg.threshold", low=0.0, low_open=True)
        _require(
            secagg.threshold < 1,
            "privacy.secagg.threshold",
            f"got {secagg.threshold!r}, must be in (0, 1)",
        )
    _check_number(secagg.corruption, "privacy.secagg.corruption", low=0.0)
    _require(
        secagg.corruption < 0.5,
        "privacy.secagg.corruption",
        f"got {secagg.corruption!r}, must be in [0, 0.5): a server with half the agents "
        "colluding learns every input from their shares",
    )
    _check_number(secagg.dropout, "privacy.secagg.dropout", low=0.0)
    _require(
        secagg.corruption + secagg.dropout < 1,
        "privacy.secagg.dropout",
        f"got {secagg.dropout!r}; corruption + dropout must be below 1",
    )
    if secagg.neighbours is not None:
        _check_int(secagg.neighbours, "privacy.secagg.neighbours", low=2)
    _check_number(secagg.range, "privacy.secagg.range", low=0.0, low_open=True)


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


@dataclass(kw_only=True)
class RunConfig:
    """One federated run."""

    seed: int = 0
    """Run seed: every agent's randomness derives from (seed, agent index, round, purpose)."""
    rounds: int = 50
    """T, the number of communication rounds."""
    plugins: list[str] = field(default_factory=list)
    """Modules to import first: they register algorithms, strategies or env families."""
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    attack: AttackConfig = field(default_factory=AttackConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    server: ServerConfig = field(default_factory=ServerConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    privacy: PrivacyConfig = field(default_factory=PrivacyConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    resume: str | None = None
    """Continue a killed run: 'true' resumes ``server.out_dir``; a path resumes that run
    directory (``fedhpg-run resume=DIR``); 'auto' resumes ``server.out_dir`` if it holds a run
    and starts one otherwise (a server its supervisor restarts with the same command)."""


# --- what each top-level key is for: the one declaration --------------------------------------


@dataclass(frozen=True, kw_only=True)
class GroupRole:
    dictated: bool
    """The server sends it in every welcome and agents adopt it (never host-specific)."""
    fixed: bool
    """It defines the run: a resumed run must keep it."""
    compared: bool
    """Runs that differ in it are different experiments: plots group by it."""
    agreed: bool = False
    """Dictated, but an agent must already hold the same: it consents instead of adopting, so
    that no server can lower what protects an agent."""


GROUPS: dict[str, GroupRole] = {
    "seed": GroupRole(dictated=True, fixed=True, compared=False),  # seeds are replicates
    "rounds": GroupRole(dictated=True, fixed=False, compared=False),  # may grow on resume
    "plugins": GroupRole(dictated=False, fixed=False, compared=False),  # each host its own
    "env": GroupRole(dictated=False, fixed=True, compared=True),  # checked at registration
    "algo": GroupRole(dictated=True, fixed=True, compared=True),
    "strategy": GroupRole(dictated=False, fixed=True, compared=True),  # the server's alone
    "agents": GroupRole(dictated=False, fixed=True, compared=True),  # each host its profile
    "attack": GroupRole(dictated=False, fixed=True, compared=True),  # attackers decide
    "policy": GroupRole(dictated=True, fixed=True, compared=True),
    "eval": GroupRole(dictated=True, fixed=False, compared=True),
    "checkpoint": GroupRole(dictated=False, fixed=False, compared=False),  # the server's files
    "server": GroupRole(dictated=False, fixed=False, compared=False),
    "agent": GroupRole(dictated=False, fixed=False, compared=False),
    "security": GroupRole(dictated=False, fixed=False, compared=False),  # paths stay on host
    "privacy": GroupRole(dictated=True, fixed=True, compared=True, agreed=True),
    "cluster": GroupRole(dictated=False, fixed=False, compared=False),  # fedhpg-cluster's jobs
    "resume": GroupRole(dictated=False, fixed=False, compared=False),
}
REPLICATE_KEYS = ("seed", "env.seed")
"""Keys whose values are replicates of one experiment (plots average over them)."""
PLACEMENT_KEYS = ("agents.per_host", "algo.memory_gib")
"""Where agents run, not what they compute (θ̃ does not depend on it): a resume may change
it, and runs that differ only in it are one experiment."""
DIAGNOSTIC_KEYS = ("algo.bound_estimates",)
"""What a run measures besides θ̃ (which does not depend on it): as free as placement."""


def groups(flag: str) -> tuple[str, ...]:
    """The top-level keys whose role has ``flag`` ('dictated', 'fixed' or 'compared')."""
    return tuple(name for name, role in GROUPS.items() if getattr(role, flag))


def dictated_settings(config: RunConfig) -> dict[str, Any]:
    """What the server sends agents: the dictated keys only (so no host's paths leave it)."""
    values = to_dict(config)
    return {key: values[key] for key in groups("dictated")}


def adopt_settings(own: RunConfig, dictated: dict[str, Any]) -> RunConfig:
    """This host's config with the server's dictated keys in place of its own; ConfigError
    where the server's value of an agreed key (privacy) differs from this host's own."""
    unknown = sorted(set(dictated) - set(groups("dictated")))
    if unknown:
        raise ConfigError(unknown[0], "the server may not dictate this key")
    values = to_dict(own)
    for group in groups("agreed"):
        if group in dictated and (differs := _first_difference(values[group], dictated[group])):
            key, mine, theirs = differs
            raise ConfigError(
                f"{group}.{key}" if key else group,
                f"the server runs {theirs!r}, this agent was started with {mine!r}: an agent "
                f"keeps its own {group} settings; start it with the server's",
            )
    return from_dict({**values, **dictated})


def _first_difference(mine: Any, theirs: Any, path: str = "") -> tuple[str, Any, Any] | None:
    """The first key (dotted; a ``mode`` first) whose values differ between two nested dicts,
    and both values."""
    if isinstance(mine, dict) and isinstance(theirs, dict):
        for key in sorted(set(mine) | set(theirs), key=lambda k: (k != "mode", k)):
            found = _first_difference(
                mine.get(key), theirs.get(key), f"{path}.{key}" if path else key
            )
            if found is not None:
                return found
        return None
    return None if mine == theirs else (path, mine, theirs)


# --- checks -----------------------------------------------------------------------------------


def per_agent(values: list[Any], index: int) -> Any:
    """Agent ``index``'s entry of a per-agent list (one entry = every agent's)."""
    return values[0] if len(values) == 1 else values[index]


def _require(condition: bool, key: str, message: str) -> None:
    if not condition:
        raise ConfigError(key, message)


def _check_choice(value: str, key: str, allowed: tuple[str, ...] | Registry[Any]) -> None:
    """``value`` one of ``allowed``: a closed tuple, or an open vocabulary's names."""
    names = allowed.names() if isinstance(allowed, Registry) else allowed
    _require(value in names, key, f"got {value!r}, allowed: {', '.join(names)}")


def _check_number(value: Any, key: str, *, low: float, low_open: bool = False) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if low_open else value >= low)
    bound = f"> {low:g}" if low_open else f">= {low:g}"
    _require(ok, key, f"got {value!r}, must be a finite number {bound}")


WIRE_INT_RANGE = (-(2**63), 2**63)
"""The integers a run's settings may hold: the wire carries signed 64-bit ones (the server
sends the config to every agent)."""


def _check_wire_ints(value: Any, key: str) -> None:
    """Every integer in ``value`` (nested dicts and lists) within :data:`WIRE_INT_RANGE`."""
    if isinstance(value, dict):
        for name, item in value.items():
            _check_wire_ints(item, f"{key}.{name}" if key else str(name))
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            _check_wire_ints(item, f"{key}[{i}]")
    elif isinstance(value, int) and not isinstance(value, bool):
        low, end = WIRE_INT_RANGE
        _require(
            low <= value < end,
            key,
            f"got {value}, beyond the signed 64-bit integers a run's settings travel as",
        )


def _check_int(value: Any, key: str, *, low: int) -> None:
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low
    _require(ok, key, f"got {value!r}, must be an integer >= {low}")


def _check_agent_list(values: Any, key: str, num_agents: int) -> None:
    _require(
        isinstance(values, list) and len(values) in (1, num_agents),
        key,
        f"needs 1 or num_agents={num_agents} values, got {values!r}",
    )


def _validate_env(env: EnvConfig) -> None:
    _check_number(env.level, "env.level", low=0.0)
    _require(env.level <= 1.0, "env.level", f"got {env.level!r}, must be in [0, 1]")
    if env.seed is not None:
        _check_int(env.seed, "env.seed", low=0)
    if env.horizon is not None:
        _check_int(env.horizon, "env.horizon", low=1)
    if env.gamma is not None:
        _check_number(env.gamma, "env.gamma", low=0.0, low_open=True)
        _require(env.gamma <= 1.0, "env.gamma", f"got {env.gamma!r}, must be in (0, 1]")
    if env.family != GYM_FAMILY:
        for key in ("id", "kwargs", "vary"):
            _require(
                not getattr(env, key),
                f"env.{key}",
                f"is read by env=gym (env.family=gym) only, not env.family={env.family}",
            )


def _validate_algo(algo: AlgoConfig) -> None:
    _check_choice(algo.estimator, "algo.estimator", ESTIMATORS)
    _check_choice(algo.baseline, "algo.baseline", BASELINES)
    _check_choice(algo.reward_to_go, "algo.reward_to_go", REWARD_TO_GO)
    _check_choice(algo.normalize, "algo.normalize", NORMALIZE)
    if not ESTIMATORS.get(algo.estimator).per_step:
        _require(
            algo.reward_to_go == "from_start",
            "algo.reward_to_go",
            f"'from_step' needs algo.estimator=gpomdp (got {algo.estimator!r})",
        )
        _require(
            algo.normalize != "episode",
            "algo.normalize",
            f"'episode' needs algo.estimator=gpomdp: {algo.estimator!r}'s coefficients are "
            "constant along a trajectory, so they would all become 0",
        )
    _check_choice(algo.optimizer, "algo.optimizer", OPTIMIZERS)
    _check_choice(algo.engine, "algo.engine", ENGINES)
    _check_choice(algo.envs, "algo.envs", ENV_PATHS)
    if algo.memory_gib is not None:
        _check_number(algo.memory_gib, "algo.memory_gib", low=0.0, low_open=True)
    _require(
        isinstance(algo.device, str) and DEVICE_PATTERN.fullmatch(algo.device) is not None,
        "algo.device",
        f"got {algo.device!r}, allowed: cpu, cuda, cuda:N",
    )
    _check_number(algo.step_size, "algo.step_size", low=0.0, low_open=True)
    if algo.grad_clip is not None:
        _check_number(algo.grad_clip, "algo.grad_clip", low=0.0, low_open=True)


def _validate_agents(agents: AgentsConfig) -> None:
    _check_int(agents.num_agents, "agents.num_agents", low=1)
    k = agents.num_agents
    for name, values in agents.budget.items():
        _check_agent_list(values, f"agents.budget.{name}", k)
    for key, values, positive in (
        ("speeds", agents.speeds, True),
        ("step_delays_s", agents.step_delays_s, False),
        ("latencies_s", agents.latencies_s, False),
        ("step_costs_s", agents.step_costs_s, False),
        ("grad_costs_s", agents.grad_costs_s, False),
        ("bandwidths_mbps", agents.bandwidths_mbps, False),
    ):
        _check_agent_list(values, f"agents.{key}", k)
        for i, value in enumerate(values):
            _check_number(value, f"agents.{key}[{i}]", low=0.0, low_open=positive)
    _check_choice(agents.schedule, "agents.schedule", SCHEDULES)
    _check_choice(agents.clock, "agents.clock", CLOCKS)
    _check_int(agents.schedule_period_rounds, "agents.schedule_period_rounds", low=1)
    _check_number(agents.schedule_amplitude, "agents.schedule_amplitude", low=0.0)
    _require(
        agents.schedule_amplitude < 1.0,
        "agents.schedule_amplitude",
        f"got {agents.schedule_amplitude!r}, must be in [0, 1)",
    )
    _check_choice(agents.plan, "agents.plan", PLANS)
    _check_int(agents.plan_every, "agents.plan_every", low=1)
    _check_number(agents.plan_round_s, "agents.plan_round_s", low=0.0)
    if agents.plan_max_return is not None:
        _check_number(agents.plan_max_return, "agents.plan_max_return", low=-math.inf)
    _check_int(agents.plan_batch_max, "agents.plan_batch_max", low=2)
    _check_int(agents.plan_local_iters_max, "agents.plan_local_iters_max", low=1)
    # agents.population: fedhpg.common.components.validate_run (its distributions are numpy's)


def _validate_attack(attack: AttackConfig, num_agents: int) -> None:
    _check_choice(attack.kind, "attack.kind", ATTACKS)
    for i, index in enumerate(attack.agents):
        _check_int(index, f"attack.agents[{i}]", low=0)
        _require(
            index < num_agents,
            f"attack.agents[{i}]",
            f"got {index}, must be < agents.num_agents={num_agents}",
        )
    _require(
        len(set(attack.agents)) == len(attack.agents),
        "attack.agents",
        f"lists an agent twice: {attack.agents}",
    )
    _check_number(attack.sign_flip_scale, "attack.sign_flip_scale", low=0.0)
    _check_number(attack.noise_scale, "attack.noise_scale", low=0.0)


def _validate_server(server: ServerConfig, num_agents: int) -> None:
    _check_int(server.port, "server.port", low=0)
    _require(server.port <= 65535, "server.port", f"got {server.port!r}, must be <= 65535")
    _check_choice(server.transport, "server.transport", TRANSPORTS)
    for key in (
        "register_timeout_s",
        "round_timeout_s",
        "round_deadline_s",
        "rejoin_timeout_s",
        "heartbeat_interval_s",
        "max_message_mb",
        "hello_timeout_s",
    ):
        _check_number(getattr(server, key), f"server.{key}", low=0.0, low_open=True)
    _check_choice(server.round_policy, "server.round_policy", ROUND_POLICIES)
    _check_int(server.min_agents, "server.min_agents", low=1)
    _require(
        server.min_agents <= num_agents,
        "server.min_agents",
        f"got {server.min_agents}, must be <= agents.num_agents={num_agents}",
    )
    _validate_buffered(server, num_agents)
    _check_int(server.heartbeat_liveness, "server.heartbeat_liveness", low=2)
    if server.max_update_norm is not None:
        _check_number(server.max_update_norm, "server.max_update_norm", low=0.0, low_open=True)
    _check_int(server.max_failed_rounds, "server.max_failed_rounds", low=0)
    if server.max_connections is not None:
        # low=1, not K: agent hosts serve many agents over one connection each
        _check_int(server.max_connections, "server.max_connections", low=1)
    _check_int(server.tensorboard_agents, "server.tensorboard_agents", low=0)


def _validate_buffered(server: ServerConfig, num_agents: int) -> None:
    if server.buffer_size is not None:
        _check_int(server.buffer_size, "server.buffer_size", low=1)
        _require(
            server.buffer_size <= num_agents,
            "server.buffer_size",
            f"got {server.buffer_size}, must be <= agents.num_agents={num_agents}",
        )
    if server.max_staleness is not None:
        _check_int(server.max_staleness, "server.max_staleness", low=0)
    _check_choice(server.staleness_weight, "server.staleness_weight", STALENESS_WEIGHTS)
    _check_number(server.diverged_share, "server.diverged_share", low=0.0, low_open=True)
    _require(
        server.diverged_share <= 1.0,
        "server.diverged_share",
        f"got {server.diverged_share!r}, must be in (0, 1]",
    )


def _validate_host_range(agent: AgentConfig, num_agents: int) -> None:
    if agent.first is None:
        return
    _check_int(agent.first, "agent.first", low=0)
    _check_int(agent.count, "agent.count", low=1)
    _require(
        agent.count <= MAX_HOST_AGENTS,
        "agent.count",
        f"got {agent.count}, more than the {MAX_HOST_AGENTS} agents one host may serve",
    )
    _require(
        agent.first + agent.count <= num_agents,
        "agent.first",
        f"the range {agent.first}..{agent.first + agent.count - 1} (agent.first, agent.count) "
        f"goes beyond the last agent index {num_agents - 1} (agents.num_agents={num_agents})",
    )


def validate(config: RunConfig) -> RunConfig:
    """Check every value this module can judge; raise :class:`ConfigError` naming the first bad
    key. The ``plugins`` are imported first, so the names they register in the vocabularies
    (:mod:`fedhpg.common.vocabularies`) are known. (Names and options of the algorithm and
    strategy registries: :func:`fedhpg.common.components.validate_run`.)"""
    _check_wire_ints(to_dict(config), "")
    _check_int(config.seed, "seed", low=0)
    _check_int(config.rounds, "rounds", low=1)
    for i, module in enumerate(config.plugins):
        _require(
            isinstance(module, str) and bool(module.strip()),
            f"plugins[{i}]",
            f"got {module!r}, must be a module name",
        )
    # before the names they may register (attacks, clocks, round policies, ...) are checked
    import_plugins(list(config.plugins))
    _validate_env(config.env)
    _validate_algo(config.algo)
    _validate_agents(config.agents)
    _validate_attack(config.attack, config.agents.num_agents)
    _validate_participation(config.strategy.participation, config.agents.num_agents)
    _validate_tolerance(config.strategy, config.agents.num_agents)

    policy = config.policy
    _require(
        isinstance(policy.hidden, list)
        and all(isinstance(h, int) and h >= 1 for h in policy.hidden),
        "policy.hidden",
        f"needs a list of positive layer widths, got {policy.hidden!r}",
    )
    _check_choice(policy.log_std, "policy.log_std", LOG_STDS)
    _require(
        isinstance(policy.name, str) and bool(policy.name.strip()),
        "policy.name",
        f"got {policy.name!r}, must be 'auto', a registered policy or package.module:Class",
    )

    _check_int(config.eval.every, "eval.every", low=1)
    _check_int(config.eval.episodes, "eval.episodes", low=1)
    if config.eval.horizon is not None:
        _check_int(config.eval.horizon, "eval.horizon", low=1)
    if config.eval.stop_at is not None:
        stop_at = config.eval.stop_at
        _require(
            isinstance(stop_at, int | float)
            and not isinstance(stop_at, bool)
            and math.isfinite(stop_at),
            "eval.stop_at",
            f"got {stop_at!r}, must be a finite return (or null: run every round)",
        )
    _require(
        isinstance(config.checkpoint.keep_best, bool),
        "checkpoint.keep_best",
        f"got {config.checkpoint.keep_best!r}, must be true or false",
    )
    if config.checkpoint.every is not None:
        _check_int(config.checkpoint.every, "checkpoint.every", low=1)

    _validate_server(config.server, config.agents.num_agents)
    _check_int(config.agent.index, "agent.index", low=0)
    _validate_host_range(config.agent, config.agents.num_agents)
    if config.agents.per_host != AUTO:
        per_host = config.agents.per_host
        _require(
            isinstance(per_host, int) and not isinstance(per_host, bool) and per_host >= 1,
            "agents.per_host",
            f"got {per_host!r}, must be 'auto' or an integer >= 1",
        )
        _require(
            int(config.agents.per_host) <= MAX_HOST_AGENTS,
            "agents.per_host",
            f"got {config.agents.per_host}, more than the {MAX_HOST_AGENTS} agents one host "
            "may serve",
        )
    _check_number(config.agent.connect_timeout_s, "agent.connect_timeout_s", low=0.0, low_open=True)
    _check_int(config.agent.max_restarts, "agent.max_restarts", low=0)
    _require(
        isinstance(config.security.curve, bool),
        "security.curve",
        f"got {config.security.curve!r}, must be true or false",
    )
    _validate_privacy(config.privacy)
    _validate_cluster(config.cluster)
    return config


def _validate_cluster(cluster: ClusterConfig) -> None:
    _check_choice(cluster.kind, "cluster.kind", CLUSTER_KINDS)
    _check_int(cluster.time_min, "cluster.time_min", low=1)
    _check_number(cluster.mem_gb, "cluster.mem_gb", low=0.0, low_open=True)
    _check_int(cluster.cpus_per_task, "cluster.cpus_per_task", low=1)
    _check_int(cluster.gpus_per_host, "cluster.gpus_per_host", low=0)
    if cluster.array_parallelism is not None:
        _check_int(cluster.array_parallelism, "cluster.array_parallelism", low=1)
    _require(
        bool(cluster.folder.strip()) and not cluster.folder.startswith("/"),
        "cluster.folder",
        f"got {cluster.folder!r}, must be a path relative to the run directory",
    )
    _check_number(cluster.endpoint_timeout_s, "cluster.endpoint_timeout_s", low=0.0, low_open=True)


def attacking_agents(run: RunConfig) -> list[int]:
    """The indices of the agents that attack (``attack.agents`` when ``attack.kind`` is set),
    in index order: what the log, the final table and metrics.jsonl mark."""
    if run.attack.kind == "none":
        return []
    return sorted({k for k in run.attack.agents if 0 <= k < run.agents.num_agents})


def agent_id_of(index: int, explicit: str | None = None) -> str:
    return explicit if explicit else f"agent-{index}"


def host_id_of(first: int, count: int, explicit: str | None = None) -> str:
    """An agent host's id (its routing identity's prefix, its CURVE key's name)."""
    return explicit if explicit else f"host-{first}-{first + count - 1}"


AUTO = "auto"
AUTO_PROCESS_AGENTS = 32
"""``agents.per_host=auto`` gives every agent its own process up to this many agents (or as
many as the machine has cores): the sleeping device emulation, per-agent restarts and
per-agent deadlines stay as written. Beyond it, a process per agent costs more than it
shows (a thousand processes on a few cores register slower than a server waits)."""


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, as a container or SLURM sets it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # not Linux
        return max(os.cpu_count() or 1, 1)


def agents_per_host(run: RunConfig, cores: int | None = None) -> int:
    """The logical agents each agent process serves: ``agents.per_host``, or for 'auto' one
    per process up to :data:`AUTO_PROCESS_AGENTS` agents (or ``cores``, default this
    machine's) and with buffered rounds (which take one agent per process), else one host
    per core."""
    per_host = run.agents.per_host
    if per_host != AUTO:
        return int(per_host)
    cores = available_cores() if cores is None else cores
    num_agents = run.agents.num_agents
    if ROUND_POLICIES.get(run.server.round_policy).asynchronous or num_agents <= max(
        AUTO_PROCESS_AGENTS, cores
    ):
        return 1
    return min(-(-num_agents // cores), MAX_HOST_AGENTS)


def host_ranges(num_agents: int, per_host: int) -> list[tuple[int, int]]:
    """(first, count) of each agent host ``fedhpg-run`` starts with ``agents.per_host``: N
    consecutive indices each, the last one the rest."""
    return [(first, min(per_host, num_agents - first)) for first in range(0, num_agents, per_host)]


def to_dict(config: RunConfig) -> dict[str, Any]:
    """Plain dict of the config (msgpack- and JSON-friendly)."""
    return dataclasses.asdict(config)


def from_dict(values: dict[str, Any]) -> RunConfig:
    """Rebuild a typed RunConfig from plain values, checking keys and types (OmegaConf)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(OmegaConf.structured(RunConfig), values)
        config = OmegaConf.to_object(merged)
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None) or "config"
        raise ConfigError(str(key), str(error).splitlines()[0]) from None
    assert isinstance(config, RunConfig)
    return validate(config)


# --- keys: typos, and what a resume may change -------------------------------------------------

FREE_DICTS = (
    "env.options",
    "env.kwargs",
    "env.vary",
    "algo.params",
    "strategy.params",
    "agents.budget",
    "agents.population.draw",
)
"""Dicts whose keys belong to a registry entry (a family's options, an algorithm's ``Params``
and ``Budget``, a strategy's ``Params``): checked by their owners, not by this schema."""


def unknown_key(values: dict[str, Any], schema: type = RunConfig, prefix: str = "") -> str | None:
    """The first key of ``values`` that ``schema`` (a config dataclass) has no field for, as a
    one-line message with the nearest known key; None when every key is known. Hydra's ``+``
    adds keys beyond the schema, which OmegaConf would drop without a word."""
    import difflib

    fields = {f.name: f for f in dataclasses.fields(schema)}
    for name, value in values.items():
        key = f"{prefix}{name}"
        if name not in fields:
            close = difflib.get_close_matches(name, fields, n=1)
            if not close:  # a typo of a nested key, e.g. rounds → server.rounds_timeout_s
                close = difflib.get_close_matches(key, all_keys(), n=1)
            else:
                close = [f"{prefix}{close[0]}"]
            hint = f"; did you mean {close[0]}?" if close else ""
            return f"{key}: not a fedhpg key{hint}"
        inner = fields[name].type
        nested = _dataclass_named(inner) if isinstance(inner, str) else None
        if nested is not None and isinstance(value, dict) and key not in FREE_DICTS:
            found = unknown_key(value, nested, f"{key}.")
            if found is not None:
                return found
    return None


def _dataclass_named(annotation: str) -> type | None:
    candidate = globals().get(annotation)
    return candidate if dataclasses.is_dataclass(candidate) else None  # type: ignore[return-value]


def all_keys(schema: type = RunConfig, prefix: str = "") -> list[str]:
    """Every dotted key of the schema (nested config dataclasses expanded)."""
    keys = []
    for f in dataclasses.fields(schema):
        nested = _dataclass_named(f.type) if isinstance(f.type, str) else None
        if nested is not None:
            keys.extend(all_keys(nested, f"{prefix}{f.name}."))
        else:
            keys.append(f"{prefix}{f.name}")
    return keys


def flatten(values: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted leaves of nested dicts: {"algo": {"step_size": 1}} → {"algo.step_size": 1}."""
    if not isinstance(values, dict) or (not values and prefix):
        return {prefix.rstrip("."): values}
    leaves: dict[str, Any] = {}
    for name, value in values.items():
        leaves.update(flatten(value, f"{prefix}{name}."))
    return leaves


def with_defaults(values: dict[str, Any]) -> dict[str, Any]:
    """A stored config (config.json, a checkpoint's copy) with every field the schema has
    now, so that a field added since it was written is not taken for a change."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(RunConfig), values))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None) or "config"
        raise ConfigError(str(key), str(error).splitlines()[0]) from None
    assert isinstance(merged, dict)
    return {str(k): v for k, v in merged.items()}


def fixed_difference(run: dict[str, Any], invocation: dict[str, Any]) -> ConfigError | None:
    """The first key that a resume must keep (``GROUPS`` fixed) and this invocation changes,
    as an error naming the dotted key and both values; None when every fixed key is kept."""
    run = with_defaults(run)
    for group in groups("fixed"):
        before = flatten(run.get(group), f"{group}.")
        after = flatten(invocation.get(group), f"{group}.")
        for key in sorted((set(before) | set(after)) - {*PLACEMENT_KEYS, *DIAGNOSTIC_KEYS}):
            old, new = before.get(key, _UNSET), after.get(key, _UNSET)
            if old != new:
                return ConfigError(
                    key,
                    f"the run has {_show(old)}, this invocation {_show(new)}; a resume keeps "
                    f"{group} as it was",
                )
    return None


_UNSET = object()


def _show(value: Any) -> str:
    return "no such key" if value is _UNSET else repr(value)
