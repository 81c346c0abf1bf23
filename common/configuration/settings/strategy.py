"""The ``strategy`` section: the server's aggregation rule, who takes part each round, and
how many faulty agents it must tolerate (read by :mod:`fedhpg.server.strategies`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.settings.algo import DEVICE_PATTERN
from fedhpg.common.configuration.settings.checks import check_choice, check_int, require

PARTICIPATION_MODES = ("all", "uniform", "trace")
TOLERANCE_CHECKS = ("refuse", "warn")


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


def validate_tolerance(strategy: StrategyConfig, num_agents: int) -> None:
    if strategy.tolerate is not None:
        check_int(strategy.tolerate, "strategy.tolerate", low=0)
        require(
            strategy.tolerate < num_agents,
            "strategy.tolerate",
            f"got {strategy.tolerate}, must be < agents.num_agents={num_agents}",
        )
    check_choice(strategy.tolerance_check, "strategy.tolerance_check", TOLERANCE_CHECKS)
    require(
        isinstance(strategy.device, str) and DEVICE_PATTERN.fullmatch(strategy.device) is not None,
        "strategy.device",
        f"got {strategy.device!r}, allowed: cpu, cuda, cuda:N",
    )


def validate_participation(participation: ParticipationConfig, num_agents: int) -> None:
    key = "strategy.participation"
    check_choice(participation.mode, f"{key}.mode", PARTICIPATION_MODES)
    if participation.mode == "uniform":
        require(
            participation.per_round is not None,
            f"{key}.per_round",
            "mode 'uniform' needs per_round, the number of agents asked each round",
        )
        check_int(participation.per_round, f"{key}.per_round", low=1)
        require(
            participation.per_round <= num_agents,  # type: ignore[operator]
            f"{key}.per_round",
            f"got {participation.per_round}, must be <= agents.num_agents={num_agents}",
        )
    if participation.mode == "trace":
        require(
            isinstance(participation.trace, str) and bool(participation.trace.strip()),
            f"{key}.trace",
            "mode 'trace' needs trace, the path of an availability CSV",
        )
    # A setting its mode ignores would be silently ignored: say which mode takes it.
    for name, mode in (("trace", "trace"), ("per_round", "uniform")):
        value = getattr(participation, name)
        require(
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
