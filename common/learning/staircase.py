"""Trajectories of different lengths, time-major, without the padding that outlasts them.

Column n of a batch holds cells t = 0 … ``extent[n]`` − 1 of trajectory n: its steps, and
either the dead steps a per-step baseline reaches (past a trajectory's end for as long as
another trajectory of its agent runs: :meth:`Staircase.of_groups`) or none (the estimator
then sums that tail once per agent). Sorted by extent, longest first and
ties in column order, the columns that still have a cell at step t are always a prefix of
that order, so step t is one contiguous run of ``widths[t]`` cells: a staircase.

A padded [T, N] batch is the staircase of N columns of extent T, and its cells are the padded
tensor's own memory. A batch whose agents' trajectories end early keeps a fraction of the
cells: CartPole's first rounds, episodes of ~20 steps padded to the longest of thousands, keep
about a sixth.

Sums along a trajectory's time run one step at a time over contiguous runs, and sums over an
agent's trajectories add its own cells in time-major order, so a column's numbers never
depend on which columns share the batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch


@dataclass(frozen=True)
class Staircase:
    """The layout of a batch's cells (see the module docstring)."""

    extents: torch.Tensor
    """[N] int64: cells of each column."""
    dense: bool = False
    """Every column has the same extent, in column order: the cells are a padded [T, N]
    tensor's memory, row-major."""
    grouped: bool = False
    """Every column has the extent of its group's longest (:meth:`of_groups`): at each step a
    group's cells are adjacent, in column order."""

    @classmethod
    def padded(cls, steps: int, columns: int, device: torch.device | str = "cpu") -> Staircase:
        """The layout of a padded [steps, columns] batch."""
        full = torch.full((columns,), steps, dtype=torch.int64, device=device)
        return cls(full, dense=True)

    @classmethod
    def of_groups(cls, lengths: torch.Tensor, groups: torch.Tensor) -> Staircase:
        """Each column extended to the longest trajectory of its group (``groups`` [N]: each
        column's agent): past that, an estimator's every term is zero."""
        if lengths.numel() == 0:
            return cls(lengths.clone())
        size = int(groups.max()) + 1
        longest = lengths.new_zeros(size).scatter_reduce(0, groups, lengths, "amax")
        return cls(longest[groups], grouped=True)

    @property
    def columns(self) -> int:
        return int(self.extents.shape[0])

    @cached_property
    def order(self) -> torch.Tensor:
        """[N]: the column at each position (longest first, ties in column order)."""
        if self.dense:
            return torch.arange(self.columns, device=self.extents.device)
        return torch.argsort(self.extents, descending=True, stable=True)

    @cached_property
    def rank(self) -> torch.Tensor:
        """[N]: each column's position."""
        if self.dense:
            return self.order
        return torch.empty_like(self.order).scatter_(
            0, self.order, torch.arange(self.columns, device=self.order.device)
        )

    @cached_property
    def widths(self) -> list[int]:
        """Cells at each step t (the columns whose extent passes t)."""
        if self.columns == 0:
            return []
        steps = int(self.extents.max())
        if self.dense:
            return [self.columns] * steps
        ending = torch.bincount(self.extents, minlength=steps + 1)[:steps]
        return (self.columns - torch.cumsum(ending, 0)).tolist()

    @cached_property
    def starts(self) -> list[int]:
        """The first cell of each step."""
        out, total = [], 0
        for width in self.widths:
            out.append(total)
            total += width
        return out

    @cached_property
    def steps(self) -> int:
        """T: the longest extent."""
        return len(self.widths)

    @cached_property
    def size(self) -> int:
        """S: the number of cells."""
        return sum(self.widths)

    @cached_property
    def time(self) -> torch.Tensor:
        """[S]: each cell's step."""
        device = self.extents.device
        widths = torch.tensor(self.widths, dtype=torch.int64, device=device)
        return torch.repeat_interleave(torch.arange(self.steps, device=device), widths)

    @cached_property
    def _step_start(self) -> torch.Tensor:
        return torch.tensor(self.starts, dtype=torch.int64, device=self.extents.device)

    def per_cell(self, values: torch.Tensor) -> torch.Tensor:
        """A per-column quantity [N, …] at every cell, [S, …] (step t's cells are the first
        ``widths[t]`` positions: one copy of each prefix)."""
        if self.columns == 0:
            return values[:0]
        return values.index_select(0, self.column)

    @cached_property
    def column(self) -> torch.Tensor:
        """[S]: each cell's column (step t's cells: the first ``widths[t]`` positions)."""
        cells = torch.arange(self.size, device=self.extents.device)
        position = cells - self._step_start.index_select(0, self.time)
        return position if self.dense else self.order.index_select(0, position)

    def cell(self, time: torch.Tensor, column: torch.Tensor) -> torch.Tensor:
        """The cell of step ``time`` of column ``column`` (inside its extent)."""
        if self.dense:
            return time * self.columns + column
        return self._step_start.index_select(0, time) + self.rank.index_select(0, column)

    def placed(self, cells: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        """``values`` [R] at ``cells`` [R] (distinct cells), zero in every other cell: [S]."""
        out = values.new_zeros((self.size, *values.shape[1:]))
        return out.index_copy_(0, cells, values)

    def gather(self, padded: torch.Tensor) -> torch.Tensor:
        """The cells of a padded [T', N, …] tensor (T' ≥ T), [S, …]."""
        flat = padded.reshape(-1, *padded.shape[2:])
        if self.dense and padded.shape[0] == self.steps:
            return flat
        return flat.index_select(0, self.time * padded.shape[1] + self.column)

    def pad(self, cells: torch.Tensor) -> torch.Tensor:
        """The cells as a padded [T, N, …] tensor (zero past each column's extent)."""
        if self.dense:
            return cells.reshape(self.steps, self.columns, *cells.shape[1:])
        out = cells.new_zeros((self.steps, self.columns, *cells.shape[1:]))
        out[self.time, self.column] = cells
        return out

    def tail_sums(self, values: torch.Tensor, factors: torch.Tensor | None = None) -> torch.Tensor:
        """R[t, n] = values[t, n] + f_n R[t + 1, n] over each column's cells, from its last
        (``factors`` [N], f = 1 without): Σ_{h ≥ t} values[h] or, with γ, Σ_{h ≥ t} γ^{h−t}
        values[h], one step at a time so no γ^{−t} is formed."""
        scale = None if factors is None else factors.to(values.dtype)[self.order]
        out = torch.empty_like(values)
        later: torch.Tensor | None = None
        for t in range(self.steps - 1, -1, -1):
            width, start = self.widths[t], self.starts[t]
            now = out[start : start + width]
            now.copy_(values[start : start + width])
            if later is not None:  # the columns that go on to step t + 1: a prefix
                carried = later if scale is None else scale[: later.shape[0]] * later
                now[: later.shape[0]] += carried
            later = now
        return out

    def step_powers(self, bases: torch.Tensor) -> torch.Tensor:
        """b_n^t at every cell (``bases`` [N]), each column's powers by repeated products
        along its own cells, so no cell's value depends on the batch's shape."""
        by_position = bases if self.dense else bases.index_select(0, self.order)
        out = bases.new_empty(self.size)
        earlier: torch.Tensor | None = None
        for t in range(self.steps):
            width, start = self.widths[t], self.starts[t]
            now = out[start : start + width]
            if earlier is None:
                now.fill_(1.0)
            else:
                torch.mul(earlier[:width], by_position[:width], out=now)
            earlier = now
        return out

    def step_group_sums(
        self, values: torch.Tensor, groups: torch.Tensor, table: Staircase
    ) -> torch.Tensor:
        """Σ values[t, n] over the columns n of each group g (``groups`` [N]) that have a cell
        at step t, added in column order, at cell (t, g) of ``table`` (a layout with a column
        per group, each as long as its longest column here). A column past its extent adds
        nothing, so a layout that stops each column early gives the same bits as one that
        pads it with zeros."""
        time = self.time
        key = table.cell(time, self.per_cell(groups))
        if not (self.dense or self.grouped):  # visit the cells column by column
            by_column = torch.argsort(self.column * max(self.steps, 1) + time)
            key, values = key.index_select(0, by_column), values.index_select(0, by_column)
        return ordered_sums(key, values, table.size)

    def per_step_group(
        self, values: torch.Tensor, groups: torch.Tensor, table: Staircase
    ) -> torch.Tensor:
        """Each cell's entry (its step, its column's group) of ``values`` on the cells of
        ``table`` (as :meth:`step_group_sums` gives them), [S]."""
        return values.index_select(0, table.cell(self.time, self.per_cell(groups)))

    def column_totals(self, values: torch.Tensor) -> torch.Tensor:
        """Σ_t values[t, n] of each column, [N] (a column's cells added from its last)."""
        if self.columns == 0:
            return values.new_zeros(0)
        return self.tail_sums(values)[: self.columns].index_select(0, self.rank)


def ordered_sums(index: torch.Tensor, values: torch.Tensor, size: int) -> torch.Tensor:
    """out[g] = Σ values[i] over the i with index[i] = g, added in the order of i from zero
    ([size, …] from ``values`` [N, …]): the same bits on every device and in any company.

    On the CPU that is ``index_add_`` (one thread adds in index order). A GPU's ``index_add_``
    adds with atomics in whatever order its threads arrive, so a sum there would change from
    run to run; elsewhere the entries of each g are laid out in a [size, most] table in their
    order and added one column at a time: the CPU's additions exactly, in ``most`` steps (the
    largest count of one g)."""
    out = values.new_zeros((size, *values.shape[1:]))
    if values.device.type == "cpu":
        return out.index_add_(0, index, values)
    return _summed_by_columns(index, values, out)


def _summed_by_columns(
    index: torch.Tensor, values: torch.Tensor, out: torch.Tensor
) -> torch.Tensor:
    """:func:`ordered_sums` without atomics (what every device other than the CPU runs): the
    entries of each g, in their order (a stable sort of ``index``, skipped where it is sorted
    already, as a staircase's cells are), added one rank at a time; only gathers, no indexed
    write (which deterministic algorithms would sort again)."""
    if index.numel() == 0:
        return out
    if bool((index[1:] >= index[:-1]).all()):
        grouped, ordered = index, values
    else:
        order = torch.argsort(index, stable=True)
        grouped, ordered = index.index_select(0, order), values.index_select(0, order)
    counts = torch.bincount(grouped, minlength=out.shape[0])
    first = torch.cumsum(counts, 0) - counts
    last = index.shape[0] - 1
    trailing = (1,) * (values.dim() - 1)
    for j in range(int(counts.max())):
        having = (counts > j).reshape(-1, *trailing)
        entry = ordered.index_select(0, (first + j).clamp_max(last))
        out += torch.where(having, entry, torch.zeros_like(entry))  # x + 0 = x: no change
    return out
