"""The trajectories of many agents' rows in one time-major batch.

Column n is one trajectory of row ``owner[n]`` (a row is one agent of the batch); every row's
columns are contiguous. The torch backend records steps padded to the longest trajectory T:
``alive[t, n]`` says whether step t of trajectory n happened, and everything at a dead step is
padding (reward 0; observation and action read by no estimator). The compiled backend hands
over the alive steps packed row by row (:class:`StepRows`), and the padded tensors are built
only if a primitive asks for them.

The torch estimator computes on :attr:`Trajectories.layout`, a
:class:`~fedhpg.common.learning.staircase.Staircase` without the padding to the batch's longest:
each trajectory reaches as far as its row's longest (every cell an estimator's terms reach).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from typing import TypeAlias, TypeVar

import numpy as np
import torch

from fedhpg.common.learning.staircase import Staircase, ordered_sums


@dataclass(frozen=True)
class StepRows:
    """The alive steps packed row after row (each row's in its backend's order)."""

    obs: torch.Tensor
    """[R, *obs_shape]."""
    actions: torch.Tensor
    """[R, *act_shape]."""
    rewards: torch.Tensor
    """[R] float64."""
    time: torch.Tensor
    """[R] each step's t."""
    column: torch.Tensor
    """[R] each step's trajectory (column of the batch)."""
    rows: torch.Tensor
    """[m] the batch row whose steps each block is."""
    row_start: torch.Tensor
    """[m + 1] block i is steps ``row_start[i]`` … ``row_start[i + 1]`` − 1."""


T = TypeVar("T")

Later: TypeAlias = "T | Callable[[], T]"
"""A value, or what makes it when it is first read (a backend that holds its batch in its own
form makes the tensors a loop reads only if one does)."""


def _made(value: Later[T]) -> T:
    return value() if callable(value) else value  # a tensor is not callable


RowSums = tuple[torch.Tensor | np.ndarray, torch.Tensor | np.ndarray]
"""Each row's (alive steps, sum of undiscounted returns): tensors, or host arrays where the
backend sampled on the host."""


class Trajectories:
    """Several rows' trajectories, time-major (see the module docstring)."""

    def __init__(
        self,
        *,
        success: Later[torch.Tensor],
        owner: Later[torch.Tensor],
        counts: torch.Tensor,
        lengths: Later[torch.Tensor] | None = None,
        rewards: torch.Tensor | None = None,
        alive: torch.Tensor | None = None,
        obs: torch.Tensor | None = None,
        actions: torch.Tensor | None = None,
        steps: Later[StepRows] | None = None,
        returns: Later[torch.Tensor] | None = None,
        row_sums: Later[RowSums] | None = None,
        sampling_s: Callable[[], float] | None = None,
        native: object = None,
    ) -> None:
        padded = rewards is not None and alive is not None and obs is not None
        if not padded and (steps is None or lengths is None):
            raise ValueError("a batch needs its steps, padded or packed with their lengths")
        self._success = success
        self._owner = owner
        self.counts = counts
        """[A] int64: trajectories per row (0 for a row that sampled none)."""
        self._steps = steps
        """The packed steps, or what makes them when :attr:`steps` is first read."""
        self._lengths = lengths
        self._returns = returns
        """Each trajectory's undiscounted return, where the backend knows it as it samples
        (the sum :meth:`returns` would add, to the bit)."""
        self._row_sums = row_sums
        """(steps, undiscounted returns) of each row, where the backend knows them as it
        samples (the sums :meth:`steps_per_row` and :meth:`returns_per_row` would add, to the
        bit)."""
        self._sampling_s = sampling_s
        self.native = native
        """The batch in its backend's own form, which only that backend reads (None: none)."""
        self._rewards, self._alive = rewards, alive
        self._obs, self._actions = obs, actions

    @property
    def success(self) -> torch.Tensor:
        """[N] bool: the episode ended in the task's goal."""
        self._success = _made(self._success)
        return self._success

    @property
    def owner(self) -> torch.Tensor:
        """[N] int64: the row each trajectory belongs to."""
        self._owner = _made(self._owner)
        return self._owner

    @property
    def steps(self) -> StepRows | None:
        """The alive steps packed row after row, where the backend packs them."""
        if self._steps is not None:
            self._steps = _made(self._steps)
        return self._steps

    # -- padded views ------------------------------------------------------------------------

    def _padded(self, values: torch.Tensor) -> torch.Tensor:
        assert self.steps is not None
        columns = int(self.owner.shape[0])
        out = values.new_zeros((self.longest, columns, *values.shape[1:]))
        out[self.steps.time, self.steps.column] = values
        return out

    @property
    def longest(self) -> int:
        """T: the longest trajectory's steps."""
        if self._alive is not None:
            return int(self._alive.shape[0])
        return int(self.lengths().max()) if self.owner.numel() else 0

    @property
    def rewards(self) -> torch.Tensor:
        """[T, N] float64."""
        if self._rewards is None:
            assert self.steps is not None
            self._rewards = self._padded(self.steps.rewards)
        return self._rewards

    @property
    def alive(self) -> torch.Tensor:
        """[T, N] bool."""
        if self._alive is None:
            assert self.steps is not None
            self._alive = self._padded(torch.ones_like(self.steps.time, dtype=torch.bool))
        return self._alive

    @property
    def obs(self) -> torch.Tensor:
        """[T, N, *obs_shape]."""
        if self._obs is None:
            assert self.steps is not None
            self._obs = self._padded(self.steps.obs)
        return self._obs

    @property
    def actions(self) -> torch.Tensor:
        """[T, N, *act_shape]: the raw sample the policy drew (before any clipping)."""
        if self._actions is None:
            assert self.steps is not None
            self._actions = self._padded(self.steps.actions)
        return self._actions

    # -- the estimator's cells ----------------------------------------------------------------

    @cached_property
    def layout(self) -> Staircase:
        """Each trajectory's cells up to its row's longest trajectory: every cell an
        estimator's terms reach (:meth:`Staircase.of_groups`)."""
        return Staircase.of_groups(self.lengths(), self.owner)

    @cached_property
    def cells(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(rewards, alive) of every cell of :attr:`layout`, [S] each."""
        layout = self.layout
        if self.steps is None:
            return layout.gather(self.rewards), layout.gather(self.alive)
        at = layout.cell(self.steps.time, self.steps.column)
        alive = torch.zeros(layout.size, dtype=torch.bool, device=at.device)
        return layout.placed(at, self.steps.rewards), alive.index_fill_(0, at, True)

    # -- per row and per trajectory -----------------------------------------------------------

    def regrouped(self, positions: torch.Tensor, rows: int) -> Trajectories:
        """The same trajectories with row i renamed ``positions[i]`` in a batch of ``rows``
        (``positions`` ascending: all ``rows`` of them leave every name as it is)."""
        if len(positions) == rows:
            return self
        counts = self.counts.new_zeros(rows)
        counts[positions] = self.counts
        steps = self._steps
        if callable(steps):  # still to be made: renamed once made
            make = steps
            steps = lambda: _renamed(make(), positions)  # noqa: E731
        elif steps is not None:
            steps = _renamed(steps, positions)
        out = Trajectories(success=self._success, owner=lambda: positions[self.owner],
                           counts=counts,
                           lengths=self._lengths, rewards=self._rewards, alive=self._alive,
                           obs=self._obs, actions=self._actions, steps=steps,
                           returns=self._returns, sampling_s=self._sampling_s,
                           native=self.native)  # fmt: skip
        # renaming rows moves no cell
        for kept in ("layout", "cells"):
            if kept in self.__dict__:
                out.__dict__[kept] = self.__dict__[kept]
        return out

    @property
    def num_rows(self) -> int:
        return int(self.counts.shape[0])

    def lengths(self) -> torch.Tensor:
        """Each trajectory's alive steps, [N]."""
        self._lengths = self.alive.sum(dim=0) if self._lengths is None else _made(self._lengths)
        return self._lengths

    def late_sampling_s(self) -> float:
        """CPU seconds the backend spent drawing the batch after its ``sample`` returned (a
        backend that draws it with its gradients, or when its steps are first read)."""
        return 0.0 if self._sampling_s is None else self._sampling_s()

    def _known_row_sums(self) -> RowSums | None:
        """The backend's own (steps, returns) of each row, made on first read (None: it has
        none)."""
        if self._row_sums is not None:
            self._row_sums = _made(self._row_sums)
        return self._row_sums

    def steps_per_row(self) -> torch.Tensor:
        """Alive steps of each row, [A] int64."""
        known = self._known_row_sums()
        if known is not None:
            return torch.as_tensor(known[0])
        return torch.zeros_like(self.counts).index_add_(0, self.owner, self.lengths())

    def row_totals(self) -> RowSums:
        """(:meth:`steps_per_row`, :meth:`returns_per_row`) as the backend holds them: host
        arrays where it sampled on the host (a round's tally reads them there)."""
        known = self._known_row_sums()
        return (self.steps_per_row(), self.returns_per_row()) if known is None else known

    def returns(self, gammas: torch.Tensor | None = None) -> torch.Tensor:
        """Each trajectory's return Σ_t γ^t r_t, [N] float64 (undiscounted without
        ``gammas``, else each column discounted by its row's γ, ``gammas`` [A])."""
        if gammas is None and self._returns is not None:
            self._returns = _made(self._returns)
            return self._returns
        rewards, _ = self.cells
        if gammas is None:  # each column's own cells in order: the same sums in any company
            return self.layout.column_totals(rewards)
        discounts = self.layout.step_powers(gammas.double().index_select(0, self.owner))
        return self.layout.column_totals(discounts * rewards)

    def per_row(self, values: torch.Tensor) -> torch.Tensor:
        """Sum of a per-trajectory [N] quantity over each row's trajectories, [A]."""
        return ordered_sums(self.owner, values, self.num_rows)

    def returns_per_row(self) -> torch.Tensor:
        """Each row's sum of its trajectories' undiscounted returns, [A] float64."""
        known = self._known_row_sums()
        if known is not None:
            return torch.as_tensor(known[1])
        return self.per_row(self.returns())


def _renamed(steps: StepRows, positions: torch.Tensor) -> StepRows:
    return replace(steps, rows=positions[steps.rows])
