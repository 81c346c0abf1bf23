"""Agents' work in one round, typed end to end.

A round's local updates are one :class:`RoundResult` from the engine to the strategy: θ rows
and the :class:`UpdateColumns` of their statistics, whose columns are generated from
:class:`UpdateStats`'s fields (the codec checks every column against these annotations);
``metrics.jsonl`` records an :class:`UpdateStats` per agent. An evaluation travels as
:class:`EvaluationStats`.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np

from fedhpg.common.records.columns import Columns, columns_of
from fedhpg.common.records.limits import (
    MAX_BATCH_ANSWERS,
    MAX_COUNT,
    AgentIndex,
    Bound,
    Count,
    Finite,
    Fraction,
    Round,
    Seconds,
    Speed,
    record_problems,
)

ALGORITHM_STATS = 32
"""Most entries an algorithm may report per round (``UpdateStats.algorithm``)."""


@dataclass(frozen=True, kw_only=True)
class UpdateStats:
    """What one round's local update cost and measured (``metrics.jsonl``'s ``agents[]``).

    Every field is bounded (:mod:`fedhpg.common.records.limits`): the codec refuses values out of
    range, and the server's update check applies the same bounds to in-process updates.
    """

    trajectories: Count
    """Trajectories sampled this round (B_k·τ_k for FedHPG, B_k + N·b_k for FedHPGVR)."""
    env_steps: Count
    """Environment steps of those trajectories (steps after an episode's end not counted)."""
    compute_s: Seconds
    """CPU time of the local update on the agent's thread (sampling, estimation, steps)."""
    train_return: Finite
    """Mean undiscounted return of the round's training trajectories."""
    grad_clipped: Count = 0
    """Local steps whose gradient was clipped to ``algo.grad_clip``."""
    emulated_s: Seconds = 0.0
    """Emulated device time: compute_s / speed + env_steps × step_delay_s (+ latency)."""
    speed: Speed = 1.0
    """The device speed during the round (after the schedule)."""
    local_wall_s: Seconds | None = None
    """Wall time the agent process spent on the round, sleeps included (distributed only)."""
    algorithm: Annotated[dict[str, Finite], Bound(max_len=ALGORITHM_STATS, key_len=64)] = field(
        default_factory=dict
    )
    """The algorithm's own per-round statistics (FedHPGVR: ``iw_mean``, ``iw_max``, ...)."""

    def problems(self) -> list[str]:
        """The bounds these stats break (none when they came through the codec)."""
        return record_problems(self)

    def to_json(self) -> dict[str, Any]:
        """The flat ``agents[]`` entry of metrics.jsonl (schema 1): algorithm stats inline,
        ``local_wall_s`` only where it was measured."""
        # the field names once per class, not dataclasses.fields() per call: metrics.jsonl
        # takes this for every agent of every round (1,000 rows a round at K = 1,000), while
        # the next round's agents train on the same cores
        values = dict(zip(ALWAYS_FIELDS, _always_values(self), strict=True))
        if self.local_wall_s is not None:
            values["local_wall_s"] = self.local_wall_s
        for name, value in self.algorithm.items():
            values[name] = float(value)
        return values


@columns_of(UpdateStats, rows=MAX_BATCH_ANSWERS)
class UpdateColumns(Columns[UpdateStats]):
    """The :class:`UpdateStats` of several agents, one list per field (item i is row i's),
    read as a sequence of records; its fields are generated from ``UpdateStats``'s
    (:func:`~fedhpg.common.records.columns.columns_of`), each column bounded as the field is.

    The one shape of a round's statistics from the agent's device pricing to the server:
    ``Update.stats`` on the wire, where the codec checks a whole column in a few C-level
    passes instead of one record at a time."""

    if TYPE_CHECKING:  # the columns columns_of generates, for the type checker
        trajectories: list[int]
        env_steps: list[int]
        compute_s: list[float]
        train_return: list[float]
        grad_clipped: list[int]
        emulated_s: list[float]
        speed: list[float]
        local_wall_s: list[float | None]
        algorithm: dict[str, list[float | None]]


_STATS_FIELDS = tuple(f.name for f in dataclasses.fields(UpdateStats))
_OPTIONAL_FIELDS = ("local_wall_s", "algorithm")
"""Written only where measured, and the algorithm's own, inline: the fields after the others."""
assert _STATS_FIELDS[-len(_OPTIONAL_FIELDS) :] == _OPTIONAL_FIELDS, "to_json's key order"
ALWAYS_FIELDS = _STATS_FIELDS[: -len(_OPTIONAL_FIELDS)]
"""The numbers every ``agents[]`` row of metrics.jsonl holds (schema 1)."""
_always_values = operator.attrgetter(*ALWAYS_FIELDS)


@dataclass(frozen=True, kw_only=True)
class EvaluationStats:
    """The unified policy's performance over ``episodes`` episodes in one agent's environment."""

    return_mean: Finite
    return_std: Finite
    discounted_return_mean: Finite
    """Mean return discounted with that agent's γ_k."""
    success_rate: Fraction
    """Fraction of episodes that reached the goal (0 where the env has no goal)."""
    length_mean: Annotated[float, Bound(low=0.0, high=MAX_COUNT, finite=True)]
    episodes: Annotated[int, Bound(low=1, high=MAX_COUNT)]

    def problems(self) -> list[str]:
        return record_problems(self)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, kw_only=True, eq=False)
class RoundResult:
    """Several agents' local updates of one round: row i of ``thetas`` is agent
    ``agents[i]``'s θ_k, ``stats[i]`` what it cost.

    The one shape of a round's result from the engine to the strategy: a group's round
    returns it (:mod:`fedhpg.common.learning.group`), the agent's device pricing fills in its device
    columns, the wire carries it as the ``update`` message (at most ``MAX_BATCH_ANSWERS`` rows
    a message: a larger result travels as slices of itself), the server concatenates a
    round's accepted rows into one, and ``Strategy.aggregate`` takes that whole. Per-agent
    records are made from it only for ``metrics.jsonl``."""

    round: Round
    agents: Annotated[list[AgentIndex], Bound(max_len=MAX_BATCH_ANSWERS)]
    """Ascending (a message's own rows; a concatenation's rows too)."""
    thetas: np.ndarray
    """float32 [A, d]."""
    stats: UpdateColumns

    def __len__(self) -> int:
        return len(self.agents)

    def __getitem__(self, rows: slice) -> RoundResult:
        """The rows ``rows`` (a slice) as a result of their own, their θ_k a view."""
        if not isinstance(rows, slice):
            raise TypeError("a RoundResult is cut by slices; theta_of / stats_of read one agent")
        return RoundResult(
            round=self.round,
            agents=self.agents[rows],
            thetas=self.thetas[rows],
            stats=self.stats[rows],
        )

    def taking(self, rows: Sequence[int]) -> RoundResult:
        """The rows at positions ``rows`` only, in that order (all of them: this result)."""
        if len(rows) == len(self.agents) and list(rows) == list(range(len(self.agents))):
            return self
        return RoundResult(
            round=self.round,
            agents=[self.agents[i] for i in rows],
            thetas=np.take(self.thetas, np.asarray(rows, dtype=np.int64), axis=0),
            stats=self.stats.take(rows),
        )

    def position(self, agent: int) -> int:
        """The row of agent ``agent`` (ValueError if it has none)."""
        return self.agents.index(agent)

    def theta_of(self, agent: int) -> np.ndarray:
        """Agent ``agent``'s θ_k (a view)."""
        return self.thetas[self.position(agent)]

    def stats_of(self, agent: int) -> UpdateStats:
        """Agent ``agent``'s statistics as a record."""
        return self.stats[self.position(agent)]

    @staticmethod
    def empty(round_index: int, num_params: int) -> RoundResult:
        """A round's result of no agent."""
        return RoundResult(
            round=round_index,
            agents=[],
            thetas=np.zeros((0, num_params), dtype=np.float32),
            stats=UpdateColumns.of([]),
        )

    def without_thetas(self, theta: np.ndarray) -> RoundResult:
        """These statistics with θ̃ (``theta``, [d]) in every row: what the server keeps of
        a securely summed round, whose θ_k it never sees (a read-only view)."""
        rows = np.broadcast_to(theta.astype(np.float32), (len(self.agents), theta.shape[0]))
        return dataclasses.replace(self, thetas=rows)

    @staticmethod
    def of_stats(round_index: int, stats: dict[int, UpdateStats], theta: np.ndarray) -> RoundResult:
        """The statistics of agents ``stats`` (by index) with θ̃ in every row
        (:meth:`without_thetas`)."""
        agents = sorted(stats)
        return RoundResult(
            round=round_index,
            agents=agents,
            thetas=np.zeros((len(agents), 0), dtype=np.float32),
            stats=UpdateColumns.of([stats[k] for k in agents]),
        ).without_thetas(theta)

    def with_stats(self, **columns: Any) -> RoundResult:
        """This result with ``columns`` in place of those of its statistics."""
        return RoundResult(
            round=self.round,
            agents=self.agents,
            thetas=self.thetas,
            stats=self.stats.replaced(**columns),
        )

    @staticmethod
    def concatenated(parts: Sequence[RoundResult]) -> RoundResult:
        """The rows of ``parts`` (results of one round, of distinct agents) in agent order."""
        assert parts, "nothing to concatenate"
        if len(parts) == 1:
            return parts[0]
        agents = [k for part in parts for k in part.agents]
        whole = RoundResult(
            round=parts[0].round,
            agents=agents,
            thetas=np.concatenate([part.thetas for part in parts]),
            stats=UpdateColumns.concatenated([part.stats for part in parts]),
        )
        order = sorted(range(len(agents)), key=agents.__getitem__)
        return whole.taking(order)


@dataclass(frozen=True, kw_only=True)
class SavedState:
    """What a stateful part (a server strategy, an optimizer) hands a checkpoint, and takes back
    on resume: JSON-like scalars and named float arrays (stored as raw bytes, never pickled)."""

    scalars: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
