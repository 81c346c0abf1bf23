"""The ``agents`` section: how many agents, their budgets, emulated devices, clock and plan."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.settings.checks import (
    check_agent_list,
    check_choice,
    check_int,
    check_number,
    require,
)
from fedhpg.common.configuration.vocabularies import CLOCKS

SCHEDULES = ("constant", "periodic", "random_walk")
PLANS = ("none", "theorem1")


@dataclass(kw_only=True)
class PopulationConfig:
    """Per-agent budgets and device profiles drawn from seeded distributions or read from a
    trace file, resolved lazily per agent index (never a K-long list): see
    :mod:`fedhpg.common.heterogeneity.population` and docs/configuration.md, "Populations"."""

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


def validate_agents(agents: AgentsConfig) -> None:
    check_int(agents.num_agents, "agents.num_agents", low=1)
    k = agents.num_agents
    for name, values in agents.budget.items():
        check_agent_list(values, f"agents.budget.{name}", k)
    for key, values, positive in (
        ("speeds", agents.speeds, True),
        ("step_delays_s", agents.step_delays_s, False),
        ("latencies_s", agents.latencies_s, False),
        ("step_costs_s", agents.step_costs_s, False),
        ("grad_costs_s", agents.grad_costs_s, False),
        ("bandwidths_mbps", agents.bandwidths_mbps, False),
    ):
        check_agent_list(values, f"agents.{key}", k)
        for i, value in enumerate(values):
            check_number(value, f"agents.{key}[{i}]", low=0.0, low_open=positive)
    check_choice(agents.schedule, "agents.schedule", SCHEDULES)
    check_choice(agents.clock, "agents.clock", CLOCKS)
    check_int(agents.schedule_period_rounds, "agents.schedule_period_rounds", low=1)
    check_number(agents.schedule_amplitude, "agents.schedule_amplitude", low=0.0)
    require(
        agents.schedule_amplitude < 1.0,
        "agents.schedule_amplitude",
        f"got {agents.schedule_amplitude!r}, must be in [0, 1)",
    )
    check_choice(agents.plan, "agents.plan", PLANS)
    check_int(agents.plan_every, "agents.plan_every", low=1)
    check_number(agents.plan_round_s, "agents.plan_round_s", low=0.0)
    if agents.plan_max_return is not None:
        check_number(agents.plan_max_return, "agents.plan_max_return", low=-math.inf)
    check_int(agents.plan_batch_max, "agents.plan_batch_max", low=2)
    check_int(agents.plan_local_iters_max, "agents.plan_local_iters_max", low=1)
    # agents.population: fedhpg.common.learning.components.validate_run (its distributions are
    # numpy's)


AUTO = "auto"
"""``agents.per_host=auto``: as many agents per process as
:func:`fedhpg.common.configuration.placement.agents_per_host` chooses."""
