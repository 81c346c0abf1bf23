"""Buffered asynchronous rounds (``server.round_policy=buffered``, FedBuff-style), in process.

No agent waits for another: each trains from the newest θ̃ it was given and, when done, its
update joins a buffer; every ``server.buffer_size`` (M) accepted updates make the next θ̃,
and those M agents restart from it. A "round" is one such aggregation, so ``metrics.jsonl``
keeps one record per version of θ̃.

The run is an event simulation ordered by emulated time: an agent dispatched at emulated time
t computes its update at once and arrives at t + the update's ``emulated_s`` (its device's
clock: with ``agents.clock=counted`` the same bit for bit on any machine); arrivals are taken
in (arrival time, agent index) order, so ties go to the lower index and a run is
deterministic. An agent's random streams and device schedule are those of its own dispatch
count (its n-th local update uses round index n), so they do not depend on the others'.

The aggregation: an update that started from θ̃_v arrives at version r − 1 with staleness
s = r − 1 − v. More than ``server.max_staleness`` and it is dropped (its agent restarts at
once from the newest θ̃). Otherwise its change Δ_k = θ_k − θ̃_v enters the buffer with weight
w(s) (``server.staleness_weight``). The configured strategy aggregates the rows
θ̃_{r−1} + w_k Δ_k: for ``mean`` that is θ̃_{r−1} + (1/M) Σ w_k Δ_k, FedBuff's rule (its
server step is 1; fedadam's server step and the robust rules apply to those rows as to
synchronous θ_k). FedBuff divides by M, not by Σ w_k: normalised by Σ w_k the weights would
cancel whenever a buffer's updates share one staleness (always, with M = 1). A fresh update
(s = 0, w = 1) is passed as θ_k itself, so with M = K every buffer
holds K fresh updates from one θ̃ and a round is bit for bit a synchronous ``wait_all`` round.

A robust rule (one that states a :meth:`~fedhpg.server.strategies.Strategy.tolerance`) is
given one row per agent instead (:func:`robust_rows`): the agents that answer fastest would
otherwise fill the buffer, and the rule's tolerance holds per aggregated set. Every agent not
in the buffer votes with its latest aggregated change, staleness-weighted, or for no change.

An update the check rejects (non-finite, too far) parks its agent until the next θ̃, so a
peer that fails at once, again and again, costs one rejection per version; the run stops as
diverged only when more than ``server.diverged_share`` of the agents were rejected since the
last θ̃, or when the buffer can no longer fill.

What continues a run exactly is :meth:`BufferedSchedule.state`: the emulated clock, each
agent's dispatch count and its in-flight update (θ_k, Δ_k, stats, base version, arrival time),
kept in the checkpoint beside θ̃.
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.ids import agent_id_of
from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.records.types import (
    EvaluationStats,
    RoundResult,
    SavedState,
    UpdateColumns,
    UpdateStats,
)
from fedhpg.server.bound_report import round_bound
from fedhpg.server.coordinator import (
    Coordinator,
    RoundRecord,
    diverged_message,
    reached_target,
    should_evaluate,
)
from fedhpg.server.pools import FederationError, RoundAnswers
from fedhpg.server.validation import Rejection, diverged, reasons

logger = logging.getLogger(__name__)


def buffer_size(run: RunConfig) -> int:
    """M: ``server.buffer_size``, or K when unset."""
    size = run.server.buffer_size
    return run.agents.num_agents if size is None else size


def staleness_weight(server: ServerConfig, staleness: int) -> float:
    """w(s) of an update ``staleness`` versions old."""
    if server.staleness_weight == "constant":
        return 1.0
    return 1.0 / math.sqrt(1.0 + staleness)


@dataclass(kw_only=True)
class InFlight:
    """One agent's update on its way: computed at dispatch, delivered at ``arrival_s``."""

    agent: int
    version: int
    """The θ̃ version it started from (0 = θ̃_0)."""
    dispatch: int
    """The agent's dispatch count: its n-th update (the round index of its random streams)."""
    arrival_s: float
    agent_id: str
    theta: torch.Tensor
    """θ_k."""
    stats: UpdateStats
    delta: torch.Tensor
    """Δ_k = θ_k − θ̃_version."""
    problem: Rejection | None = None
    """Why the update check rejected it (it arrives, but is not aggregated)."""

    def key(self) -> tuple[float, int]:
        return (self.arrival_s, self.agent)


def _weighted_row(
    server: ServerConfig, theta: torch.Tensor, version: int, delta: torch.Tensor, current: int
) -> torch.Tensor:
    """θ̃ + w(s) Δ for a change Δ started from version ``version``, at version ``current``."""
    weight = staleness_weight(server, current - version)
    return (theta + weight * delta).to(theta.dtype)


Row = tuple[int, torch.Tensor, UpdateStats]
"""An agent index, the θ row the strategy aggregates for it, the stats of its update."""


def buffer_rows(
    server: ServerConfig, theta: torch.Tensor, buffer: Sequence[InFlight], current: int
) -> list[Row]:
    """The rows the strategy aggregates into the next θ̃ from θ̃ = ``theta`` (version
    ``current``): θ̃ + w(s_k) Δ_k, or θ_k itself where that is the same number (a fresh update,
    w = 1), in agent order."""
    rows = []
    for item in sorted(buffer, key=lambda i: i.agent):
        if item.version == current:  # w(0) = 1 under every weighting
            row = item.theta
        else:
            row = _weighted_row(server, theta, item.version, item.delta, current)
        rows.append((item.agent, row, item.stats))
    return rows


def rows_result(version: int, rows: Sequence[Row]) -> RoundResult:
    """``rows`` as the result the strategy aggregates into θ̃ version ``version``."""
    return RoundResult(
        round=version,
        agents=[k for k, _, _ in rows],
        thetas=torch.stack([row for _, row, _ in rows]).numpy(),
        stats=UpdateColumns.of([stats for _, _, stats in rows]),
    )


@dataclass(frozen=True)
class Contribution:
    """An agent's latest aggregated change: what a robust rule's set keeps voting with."""

    version: int
    delta: torch.Tensor


NO_WORK = UpdateStats(trajectories=0, env_steps=0, compute_s=0.0, train_return=0.0)
"""The stats of a row that stands for an agent not heard from (it votes for no change)."""


def robust_rows(
    server: ServerConfig,
    theta: torch.Tensor,
    buffer: Sequence[InFlight],
    latest: dict[int, Contribution],
    agents: Sequence[int],
    current: int,
) -> list[Row]:
    """A robust rule's set in buffered rounds: one row per agent, never one per arrival, so
    agents that answer fastest cannot fill the set. The buffer's updates as in
    :func:`buffer_rows`; every other agent's latest aggregated change Δ again, weighted by its
    staleness (no change, θ̃ itself, where it has none yet or it is older than
    ``server.max_staleness``). The rule then tolerates its share of K rows, not of M."""
    arrived = {item.agent: item for item in buffer}
    limit = server.max_staleness
    rows = []
    for k in agents:
        item = arrived.get(k)
        if item is not None:
            rows.extend(buffer_rows(server, theta, [item], current))
            continue
        kept = latest.get(k)
        row = theta
        if kept is not None and (limit is None or current - kept.version <= limit):
            row = _weighted_row(server, theta, kept.version, kept.delta, current)
        rows.append((k, row, NO_WORK))
    return rows


@dataclass(kw_only=True)
class BufferedSchedule:
    """The in-flight updates (one per agent at most), the emulated clock, the dispatch counts."""

    clock_s: float = 0.0
    dispatches: dict[int, int] = field(default_factory=dict)
    in_flight: dict[int, InFlight] = field(default_factory=dict)
    latest: dict[int, Contribution] = field(default_factory=dict)
    """A robust rule's memory: each agent's latest aggregated change (:func:`robust_rows`)."""
    _queue: list[tuple[float, int]] = field(default_factory=list)
    """A heap of (arrival time, agent index): the order arrivals are taken in."""

    def push(self, item: InFlight) -> None:
        self.in_flight[item.agent] = item
        heapq.heappush(self._queue, (item.arrival_s, item.agent))

    def pop(self) -> InFlight:
        _, agent = heapq.heappop(self._queue)
        item = self.in_flight.pop(agent)
        self.clock_s = max(self.clock_s, item.arrival_s)
        return item

    def state(self) -> SavedState:
        arrays: dict[str, np.ndarray] = {}
        flights = []
        for agent, item in sorted(self.in_flight.items()):
            arrays[f"theta.{agent}"] = item.theta.numpy().copy()
            arrays[f"delta.{agent}"] = item.delta.numpy().copy()
            flights.append(
                {
                    "agent": agent,
                    "version": item.version,
                    "dispatch": item.dispatch,
                    "arrival_s": item.arrival_s,
                    "problem": None if item.problem is None else item.problem.saved(),
                    "stats": dataclasses.asdict(item.stats),
                }
            )
        for agent, kept in sorted(self.latest.items()):
            arrays[f"latest.{agent}"] = kept.delta.numpy().copy()
        scalars = {
            "clock_s": self.clock_s,
            "dispatches": [[k, n] for k, n in sorted(self.dispatches.items())],
            "in_flight": flights,
            "latest": [[k, kept.version] for k, kept in sorted(self.latest.items())],
        }
        return SavedState(scalars=scalars, arrays=arrays)

    @classmethod
    def restore(cls, state: SavedState) -> BufferedSchedule:
        schedule = cls(
            clock_s=float(state.scalars["clock_s"]),
            dispatches={int(k): int(n) for k, n in state.scalars["dispatches"]},
            latest={
                int(k): Contribution(int(v), torch.from_numpy(state.arrays[f"latest.{k}"].copy()))
                for k, v in state.scalars.get("latest", [])
            },
        )
        for flight in state.scalars["in_flight"]:
            agent = int(flight["agent"])
            schedule.push(
                InFlight(
                    agent=agent,
                    version=int(flight["version"]),
                    dispatch=int(flight["dispatch"]),
                    arrival_s=float(flight["arrival_s"]),
                    agent_id=agent_id_of(agent),
                    theta=torch.from_numpy(state.arrays[f"theta.{agent}"].copy()),
                    stats=UpdateStats(**flight["stats"]),
                    delta=torch.from_numpy(state.arrays[f"delta.{agent}"].copy()),
                    problem=None
                    if flight["problem"] is None
                    else Rejection.restore(flight["problem"]),
                )
            )
        return schedule


class CheckingPool(Protocol):
    """A pool whose updates are computed at once, checked (the in-process pool)."""

    def checked_result(
        self, round_index: int, theta: torch.Tensor, agents: Sequence[int]
    ) -> tuple[RoundResult, list[Rejection | None]]: ...

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]: ...


class BufferedCoordinator(Coordinator):
    """The round loop of :mod:`fedhpg.server.buffered` over the in-process pool."""

    pool: CheckingPool  # type: ignore[assignment]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.size = buffer_size(self.run)
        saved = self.progress.schedule_state  # a resumed run's in-flight updates
        self.schedule = BufferedSchedule.restore(saved) if saved is not None else None
        self.parked: list[int] = []
        """Agents whose update was rejected since the last θ̃: restarted with the next one."""

    def _dispatch(self, agents: Sequence[int], version: int, at_s: float) -> None:
        """Start ``agents`` from θ̃ (version ``version``) at emulated time ``at_s``."""
        assert self.schedule is not None
        by_count: dict[int, list[int]] = {}
        for k in agents:
            count = self.schedule.dispatches.get(k, 0) + 1
            self.schedule.dispatches[k] = count
            by_count.setdefault(count, []).append(k)
        # Agents of one dispatch count train as one group call (the batched engine's batch);
        # an agent's result never depends on whom it is batched with.
        for count, chosen in sorted(by_count.items()):
            result, problems = self.pool.checked_result(count, self.theta, chosen)
            records = result.stats.records()
            for i, (k, problem) in enumerate(zip(result.agents, problems, strict=True)):
                theta = torch.from_numpy(result.thetas[i])
                self.schedule.push(
                    InFlight(
                        agent=k,
                        version=version,
                        dispatch=count,
                        arrival_s=at_s + records[i].emulated_s,
                        agent_id=agent_id_of(k),
                        theta=theta,
                        stats=records[i],
                        delta=theta - self.theta,
                        problem=problem,
                    )
                )

    def _fill_buffer(
        self, version: int
    ) -> tuple[list[InFlight], dict[str, int], dict[str, Rejection]]:
        """Arrivals until M accepted ones. A stale agent restarts at once from the newest θ̃; an
        agent whose update is rejected waits for the next θ̃ (:attr:`parked`), so one peer that
        keeps failing costs one rejection per version and never ends the run by itself."""
        assert self.schedule is not None
        buffer: list[InFlight] = []
        stale: dict[str, int] = {}
        failures: dict[str, Rejection] = {}
        limit = self.run.server.max_staleness
        while len(buffer) < self.size:
            if len(buffer) + self._outstanding() < self.size:
                raise FederationError(self._unfillable(version, len(buffer), failures))
            item = self._next_arrival()
            self.progress.trajectories_per_agent += (
                item.stats.trajectories / self.run.agents.num_agents
            )
            staleness = version - 1 - item.version
            if item.problem is not None:
                failures[item.agent_id] = item.problem
                self.parked.append(item.agent)
                if len(self.parked) > self.run.server.diverged_share * self.run.agents.num_agents:
                    raise FederationError(self._diverged(version, failures))
                continue
            if limit is not None and staleness > limit:
                logger.debug("dropped %s's update: staleness %d", item.agent_id, staleness)
                stale[item.agent_id] = staleness
                self._dispatch([item.agent], version - 1, item.arrival_s)
                continue
            buffer.append(item)
        return buffer, stale, failures

    def _diverged(self, version: int, failures: dict[str, Rejection]) -> str:
        if diverged(failures):
            return diverged_message(self.run, version)
        share = self.run.server.diverged_share
        return (
            f"round {version}: the updates of {len(failures)} of {self.run.agents.num_agents} "
            f"agents were rejected, more than server.diverged_share={share:g} of them "
            f"({reasons(failures)})"
        )

    def _unfillable(self, version: int, accepted: int, failures: dict[str, Rejection]) -> str:
        if diverged(failures):
            return diverged_message(self.run, version)
        return (
            f"round {version}: {accepted} updates accepted and no more can come, "
            f"server.buffer_size={self.size} needed (rejected: {reasons(failures)})"
        )

    def _outstanding(self) -> int:
        """Updates still to arrive (computed or in flight) that could fill the buffer."""
        assert self.schedule is not None
        return len(self.schedule.in_flight)

    def _rows(self, buffer: Sequence[InFlight], current: int) -> RoundResult:
        """What the strategy aggregates: the buffer, or for a robust rule (one that states a
        tolerance) one row per agent, its latest change (:func:`robust_rows`)."""
        assert self.schedule is not None
        server = self.run.server
        if self.strategy.tolerance(len(buffer)) is None:
            return rows_result(current + 1, buffer_rows(server, self.theta, buffer, current))
        latest = self.schedule.latest
        rows = robust_rows(server, self.theta, buffer, latest, self._agents(), current)
        for item in buffer:
            latest[item.agent] = Contribution(item.version, item.delta)
        return rows_result(current + 1, rows)

    def _next_arrival(self) -> InFlight:
        assert self.schedule is not None
        return self.schedule.pop()

    def _agents(self) -> Sequence[int]:
        return range(self.run.agents.num_agents)

    def _restart(self, version: int, agents: Sequence[int]) -> None:
        """Restart ``agents`` (the aggregated and the parked ones) from the new θ̃ (version
        ``version``)."""
        assert self.schedule is not None
        self._dispatch(agents, version, self.schedule.clock_s)

    def _evaluate(self, version: int) -> dict[str, EvaluationStats]:
        return self.pool.evaluate(version, self.theta, self.run.eval.episodes)

    def run_rounds(self) -> torch.Tensor:
        started = time.perf_counter() - self.progress.elapsed_s
        if self.schedule is None:
            self.schedule = BufferedSchedule()
        # every agent not in flight (all of them at the start; on resuming a checkpoint of
        # agent processes, whose in-flight work stayed with them) starts from θ̃
        idle = [k for k in self._agents() if k not in self.schedule.in_flight]
        if idle:
            self._dispatch(idle, self.progress.next_round - 1, self.schedule.clock_s)
        for version in range(self.progress.next_round, self.run.rounds + 1):
            round_started = time.perf_counter()
            buffer, stale, failures = self._fill_buffer(version)
            rows = self._rows(buffer, version - 1)
            self._aggregate(version, RoundAnswers(result=rows, failures=failures), len(rows))
            restarted, self.parked = sorted([i.agent for i in buffer] + self.parked), []
            self._restart(version, restarted)
            round_time = time.perf_counter() - round_started
            evaluation = self._evaluate(version) if should_evaluate(self.run, version) else None
            wall_time = time.perf_counter() - started
            progress = self.progress
            progress.next_round = version + 1
            progress.elapsed_s = wall_time
            progress.strategy_state = self.strategy.state()
            progress.schedule_state = self.schedule.state()
            ordered = sorted(buffer, key=lambda i: i.agent)
            aggregated = rows_result(version, [(i.agent, i.theta, i.stats) for i in ordered])
            names = {i.agent: i.agent_id for i in ordered}
            record = RoundRecord(
                round=version,
                wall_time_s=wall_time,
                round_time_s=round_time,
                result=aggregated,
                name=names.__getitem__,
                trajectories_per_agent=progress.trajectories_per_agent,
                eval=evaluation,
                failures=reasons(failures),
                selected=[i.agent for i in ordered],
                emulated_clock_s=self.schedule.clock_s,
                staleness=[version - 1 - i.version for i in ordered],
                stale=stale,
                bound=round_bound(self.run, aggregated) if self.run.algo.bound_estimates else None,
                strategy=self.strategy.round_stats(),
            )
            for callback in self.on_round:
                callback(record, self.theta)
            if reached_target(self.run, version, evaluation):
                self.stopped_early = version
                break
        return self.theta
