"""Participation: which agents are asked to train each round (``strategy.participation``).

Applied by the coordinator before any strategy's own ``select``, so every strategy, a plugin's
included, gets it: the strategy chooses among the participating agents.

- ``all``: every agent, every round (the paper).
- ``uniform``: ``per_round`` distinct agents drawn uniformly from a generator seeded by
  (run seed, round) alone. Nothing is kept between rounds, so a resumed run, or the
  in-process and the distributed runtimes, select exactly the same agents. A DP run
  (``privacy=dp`` or ``dp_secagg``) is accounted with amplification by this sampling, which
  holds only while the sample is secret: its sample is drawn from the operating system's
  CSPRNG and written nowhere (a resumed run draws afresh), or, with ``privacy.noise_seed``,
  from (noise seed, round): reproducible, and known to whoever knows the seed.
- ``trace``: the agents a CSV file does not mark offline in that round. A round in which
  every agent is offline is a configuration error, reported before the run starts.

The trace format: a header ``agent,offline_from,offline_to`` then one row per offline
interval (rounds inclusive, from 1); an agent may have several rows, an agent without a row is
always available, and lines starting with ``#`` are comments.
"""

from __future__ import annotations

import csv
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.strategy import ParticipationConfig

TRACE_KEY = "strategy.participation.trace"
TRACE_COLUMNS = ("agent", "offline_from", "offline_to")
SELECTION_STREAM = 0x5E1EC7
"""Tags the draw's seed, so it shares no stream with an agent's (seed, agent, round, purpose)."""


@dataclass(frozen=True)
class OfflineInterval:
    agent: int
    first_round: int
    last_round: int

    def covers(self, round_number: int) -> bool:
        return self.first_round <= round_number <= self.last_round


def read_trace(path: str, num_agents: int) -> list[OfflineInterval]:
    """The offline intervals of a trace file; ConfigError naming the file and row if wrong."""
    file = Path(path)
    if not file.is_file():
        raise ConfigError(TRACE_KEY, f"no such file: {path}")
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(TRACE_KEY, f"cannot read {path}: {error}") from None
    rows = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ConfigError(TRACE_KEY, f"{path} is empty; needs a header {','.join(TRACE_COLUMNS)}")
    header_line, header = rows[0]
    if tuple(cell.strip() for cell in next(csv.reader([header]))) != TRACE_COLUMNS:
        raise ConfigError(
            TRACE_KEY,
            f"{path} line {header_line}: the header must be {','.join(TRACE_COLUMNS)}, "
            f"got {header.strip()!r}",
        )
    intervals = []
    for number, line in rows[1:]:
        cells = [cell.strip() for cell in next(csv.reader([line]))]
        where = f"{path} line {number}"
        if len(cells) != len(TRACE_COLUMNS) or not all(c.isdigit() for c in cells):
            raise ConfigError(
                TRACE_KEY, f"{where}: needs three non-negative integers, got {line.strip()!r}"
            )
        agent, first, last = (int(c) for c in cells)
        if agent >= num_agents:
            raise ConfigError(
                TRACE_KEY, f"{where}: agent {agent} is not < agents.num_agents={num_agents}"
            )
        if not 1 <= first <= last:
            raise ConfigError(
                TRACE_KEY, f"{where}: needs 1 <= offline_from <= offline_to, got {first}, {last}"
            )
        intervals.append(OfflineInterval(agent, first, last))
    return intervals


class Participation:
    """Who is asked to train in a round; a function of the round alone (no state), unless the
    draw is ``secret``."""

    def __init__(
        self,
        config: ParticipationConfig,
        *,
        seed: int,
        num_agents: int,
        offline: Sequence[OfflineInterval] = (),
        secret: bool = False,
    ) -> None:
        self.config = config
        self.seed = seed
        """The draw's seed: the run's, or for a secret draw ``privacy.noise_seed``'s."""
        self.num_agents = num_agents
        self.offline = list(offline)
        self.secret = secret
        """``uniform``: draw from the operating system's CSPRNG, not from ``seed``."""

    def select(self, round_number: int) -> list[int]:
        """The participating agent indices of ``round_number``, in increasing order."""
        agents = range(self.num_agents)
        if self.config.mode == "uniform":
            assert self.config.per_round is not None  # validated
            if self.secret:
                chosen = secrets.SystemRandom().sample(agents, self.config.per_round)
                return sorted(chosen)
            rng = np.random.default_rng([self.seed, round_number, SELECTION_STREAM])
            drawn = rng.choice(self.num_agents, size=self.config.per_round, replace=False)
            return sorted(int(k) for k in drawn)
        if self.config.mode == "trace":
            away = {i.agent for i in self.offline if i.covers(round_number)}
            return [k for k in agents if k not in away]
        return list(agents)


def make_participation(run: RunConfig) -> Participation:
    """The run's participation rule (reads the trace file of mode 'trace'); a DP run's uniform
    draw is secret, or seeded by ``privacy.noise_seed`` where set."""
    config = run.strategy.participation
    num_agents = run.agents.num_agents
    offline: list[OfflineInterval] = []
    if config.mode == "trace":
        assert config.trace is not None  # validated
        offline = read_trace(config.trace, num_agents)
    seed, secret = run.seed, False
    if run.privacy.mode in ("dp", "dp_secagg"):
        noise_seed = run.privacy.noise_seed
        seed, secret = (run.seed, True) if noise_seed is None else (noise_seed, False)
    return Participation(config, seed=seed, num_agents=num_agents, offline=offline, secret=secret)


def smallest_participation(run: RunConfig) -> tuple[int, str]:
    """The fewest agents any round of ``run`` asks, and the setting that makes it so."""
    config = run.strategy.participation
    if config.mode == "uniform":
        assert config.per_round is not None  # validated
        return config.per_round, f"strategy.participation.per_round={config.per_round}"
    if config.mode == "trace":
        participation = make_participation(run)
        counts = [len(participation.select(r)) for r in range(1, run.rounds + 1)]
        fewest = min(counts)
        sparsest = counts.index(fewest) + 1
        return fewest, f"round {sparsest} of {config.trace}"
    return run.agents.num_agents, f"every one of agents.num_agents={run.agents.num_agents}"


def validate_participation(run: RunConfig) -> None:
    """Server-side checks: the trace parses and leaves somebody available in every round."""
    make_participation(run)
    if run.strategy.participation.mode != "trace":
        return
    fewest, where = smallest_participation(run)
    if not fewest:
        raise ConfigError(
            TRACE_KEY,
            f"every agent is offline in {where}; a round needs at least one agent",
        )
