"""A group's round column-wise: every agent's θ_k as a row of one [A, d] array, every field of
their :class:`~fedhpg.common.types.UpdateStats` as one array, every local iteration's work
(what the device emulation prices) as arrays over the agents that ran it.

An agent host of many agents would spend more time on per-agent objects than on its engine
if it built an ``UpdateStats`` per agent and iteration and then the wire's columns back from
them. :func:`train_columns` gives the host the round in the shape it sends, straight from a
group that computes columns (:meth:`EngineGroup.train_columns
<fedhpg.common.group.EngineGroup.train_columns>`), or gathered from any other group's
per-agent results. A group's per-agent ``train`` reads its records out of the same arrays
(:meth:`TrainedColumns.result`), so an agent's statistics do not depend on which of the two
a placement calls.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from fedhpg.common.group import AgentGroup, Budgets
from fedhpg.common.types import LocalResult, UpdateColumns, UpdateStats
from fedhpg.common.worker import IterationWork

Interrupt = Callable[[], None]
"""Called between local iterations; it may raise to cancel the round (a host's does when the
server supersedes the request)."""


@dataclass(frozen=True)
class IterationColumns:
    """One local iteration of the round's agents at ``positions`` (rows of the round)."""

    positions: np.ndarray
    """int64 rows of :attr:`TrainedColumns.agents` that ran this iteration."""
    compute_s: np.ndarray
    """float64 thread CPU seconds each one's iteration took here."""
    env_steps: np.ndarray
    """int64."""
    grad_steps: np.ndarray
    """int64 trajectory steps differentiated."""


@dataclass(frozen=True)
class TrainedColumns:
    """The round's local updates of ``agents`` (ascending): item i of every column is
    ``agents[i]``'s. The device fields of ``UpdateStats`` are not here: the caller's device
    emulation fills them in from :attr:`iterations`."""

    agents: list[int]
    thetas: np.ndarray
    """float32 [A, d]: row i is θ_i."""
    trajectories: np.ndarray
    env_steps: np.ndarray
    compute_s: np.ndarray
    train_return: np.ndarray
    grad_clipped: np.ndarray
    algorithm: dict[str, list[float | None]] = field(default_factory=dict)
    """Each algorithm statistic's column of Python floats; None where an agent has none."""
    iterations: list[IterationColumns] = field(default_factory=list)
    """In the order they ran; an agent's own iterations in its order."""

    def stats(self, **device: Any) -> UpdateColumns:
        """The round's :class:`UpdateStats` as columns: the fields this round computed, each
        of ``device`` (the emulated device's columns: ``emulated_s``, ``speed``, ...), the
        other fields at their defaults."""
        own = {
            name: getattr(self, name)
            for name in (*UpdateColumns.scalar_fields, *UpdateColumns.map_fields)
            if name not in device and hasattr(self, name)
        }
        return UpdateColumns.filled(len(self.agents), **own, **device)

    @functools.cached_property
    def _records(self) -> list[UpdateStats]:
        return self.stats().records()

    def record(self, i: int) -> UpdateStats:
        """Row i as the per-agent record (``UpdateStats``'s device fields at their defaults)."""
        return self._records[i]

    def result(self, i: int) -> LocalResult:
        return LocalResult(theta=torch.from_numpy(self.thetas[i]), stats=self.record(i))

    def lone_result(self) -> LocalResult:
        """:meth:`result` of a round of one agent, without the columns' records (a lone agent
        pays for one record, not for the machinery of many)."""
        assert len(self.agents) == 1
        stats = UpdateStats(
            trajectories=int(self.trajectories[0]),
            env_steps=int(self.env_steps[0]),
            compute_s=float(self.compute_s[0]),
            train_return=float(self.train_return[0]),
            grad_clipped=int(self.grad_clipped[0]),
            algorithm={
                name: value
                for name, column in self.algorithm.items()
                if (value := column[0]) is not None
            },
        )
        return LocalResult(theta=torch.from_numpy(self.thetas[0]), stats=stats)


@runtime_checkable
class ColumnGroup(Protocol):
    """A group that computes its round as columns itself."""

    def train_columns(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Budgets | None = None,
        interrupt: Interrupt | None = None,
    ) -> TrainedColumns: ...


def train_columns(
    group: AgentGroup,
    round_index: int,
    theta: torch.Tensor,
    agents: Sequence[int],
    *,
    budgets: Budgets | None = None,
    interrupt: Interrupt | None = None,
) -> TrainedColumns:
    """``group``'s round of ``agents`` as columns: its own where it computes them, else its
    per-agent results and iterations gathered into columns (the same numbers)."""
    if isinstance(group, ColumnGroup):
        return group.train_columns(round_index, theta, agents, budgets=budgets, interrupt=interrupt)
    order = sorted(agents)
    row = {k: i for i, k in enumerate(order)}
    works: list[list[tuple[int, IterationWork]]] = []
    seen = dict.fromkeys(order, 0)

    def on_iteration(k: int, work: IterationWork) -> None:
        if interrupt is not None:
            interrupt()
        n = seen[k]
        seen[k] = n + 1
        if n == len(works):
            works.append([])
        works[n].append((row[k], work))

    results = group.train(round_index, theta, order, on_iteration=on_iteration, budgets=budgets)
    return gathered(order, [results[k] for k in order], works)


def gathered(
    order: list[int], results: Sequence[LocalResult], works: list[list[tuple[int, IterationWork]]]
) -> TrainedColumns:
    """Per-agent results (of ``order``, in order) and each agent's n-th iteration in
    ``works[n]`` as columns."""
    stats = [r.stats for r in results]
    names = dict.fromkeys(key for s in stats for key in s.algorithm)
    return TrainedColumns(
        agents=order,
        thetas=np.stack([r.theta.detach().numpy() for r in results]).astype(np.float32, copy=False),
        trajectories=np.array([s.trajectories for s in stats], dtype=np.int64),
        env_steps=np.array([s.env_steps for s in stats], dtype=np.int64),
        compute_s=np.array([s.compute_s for s in stats], dtype=np.float64),
        train_return=np.array([s.train_return for s in stats], dtype=np.float64),
        grad_clipped=np.array([s.grad_clipped for s in stats], dtype=np.int64),
        algorithm={
            key: [None if (value := s.algorithm.get(key)) is None else float(value) for s in stats]
            for key in names
        },
        iterations=[
            IterationColumns(
                positions=np.array([i for i, _ in column], dtype=np.int64),
                compute_s=np.array([w.compute_s for _, w in column], dtype=np.float64),
                env_steps=np.array([w.env_steps for _, w in column], dtype=np.int64),
                grad_steps=np.array([w.grad_steps for _, w in column], dtype=np.int64),
            )
            for column in works
        ],
    )
