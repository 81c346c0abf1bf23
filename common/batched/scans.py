"""The staircase's primitives compiled (numba), for the compiled backend's batches on the CPU.

:class:`~fedhpg.common.staircase.Staircase` runs its scans along time (reward-to-go tail
sums, powers γ^t) one step at a time, a few torch calls a step: on a GPU each call is wide,
on a CPU a batch of short episodes pays the calls' overhead at every step of its longest
episode; its index arithmetic (sorting columns by extent, a cell's place, each agent's sums
at each step) is a handful of passes over every cell in torch, one here. These kernels run
the same recurrences in the same order (step by step, the cells of a step in position order,
an agent's columns in column order, no fused multiply-add: LLVM may not contract without
``fastmath``), so they give the torch code's bits; ``tests/test_compiled_engine.py`` checks
that they do.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from fedhpg.common.staircase import Staircase


@njit(cache=True, error_model="numpy")
def _tail_sums(
    values: np.ndarray, widths: np.ndarray, starts: np.ndarray, scale: np.ndarray, out: np.ndarray
) -> None:
    scaled = scale.shape[0] > 0
    for t in range(widths.shape[0] - 1, -1, -1):
        start, width = starts[t], widths[t]
        carried = widths[t + 1] if t + 1 < widths.shape[0] else 0
        later = starts[t + 1] if t + 1 < widths.shape[0] else 0
        for p in range(carried):
            term = scale[p] * out[later + p] if scaled else out[later + p]
            out[start + p] = values[start + p] + term
        for p in range(carried, width):
            out[start + p] = values[start + p]


@njit(cache=True, error_model="numpy")
def _step_powers(
    bases: np.ndarray, widths: np.ndarray, starts: np.ndarray, out: np.ndarray
) -> None:
    for p in range(widths[0] if widths.shape[0] else 0):
        out[p] = 1.0
    for t in range(1, widths.shape[0]):
        start, earlier = starts[t], starts[t - 1]
        for p in range(widths[t]):
            out[start + p] = out[earlier + p] * bases[p]


@njit(cache=True, error_model="numpy")
def _cells(
    widths: np.ndarray, starts: np.ndarray, order: np.ndarray, time: np.ndarray, column: np.ndarray
) -> None:
    for t in range(widths.shape[0]):
        start = starts[t]
        for p in range(widths[t]):
            time[start + p] = t
            column[start + p] = order[p]


@njit(cache=True, error_model="numpy")
def _cell(
    starts: np.ndarray, rank: np.ndarray, time: np.ndarray, column: np.ndarray, out: np.ndarray
) -> None:
    for i in range(time.shape[0]):
        out[i] = starts[time[i]] + rank[column[i]]


@njit(cache=True, error_model="numpy")
def _step_group_sums(
    extents: np.ndarray,
    starts: np.ndarray,
    rank: np.ndarray,
    groups: np.ndarray,
    table_starts: np.ndarray,
    table_rank: np.ndarray,
    values: np.ndarray,
    out: np.ndarray,
) -> None:
    for n in range(extents.shape[0]):  # column by column: each sum in column order
        place, row = rank[n], table_rank[groups[n]]
        for t in range(extents[n]):
            out[table_starts[t] + row] += values[starts[t] + place]


@njit(cache=True, error_model="numpy")
def _per_step_group(
    widths: np.ndarray,
    starts: np.ndarray,
    order: np.ndarray,
    groups: np.ndarray,
    table_starts: np.ndarray,
    table_rank: np.ndarray,
    values: np.ndarray,
    out: np.ndarray,
) -> None:
    for t in range(widths.shape[0]):
        start, row_start = starts[t], table_starts[t]
        for p in range(widths[t]):
            out[start + p] = values[row_start + table_rank[groups[order[p]]]]


@njit(cache=True, error_model="numpy")
def _arrangement(
    extents: np.ndarray, order: np.ndarray, rank: np.ndarray, widths: np.ndarray
) -> None:
    """A counting sort by extent, longest first, ties in column order."""
    steps = widths.shape[0]
    ending = np.zeros(steps + 1, dtype=np.int64)  # columns of each extent
    for n in range(extents.shape[0]):
        ending[extents[n]] += 1
    next_place = np.zeros(steps + 1, dtype=np.int64)
    placed = 0
    for extent in range(steps, -1, -1):
        next_place[extent] = placed
        placed += ending[extent]
    for n in range(extents.shape[0]):
        place = next_place[extents[n]]
        next_place[extents[n]] = place + 1
        order[place], rank[n] = n, place
    alive = extents.shape[0]
    for t in range(steps):
        alive -= ending[t]
        widths[t] = alive


@njit(cache=True, error_model="numpy")
def _per_cell(widths: np.ndarray, starts: np.ndarray, order: np.ndarray, values: np.ndarray,
              out: np.ndarray) -> None:  # fmt: skip
    for t in range(widths.shape[0]):
        start = starts[t]
        for p in range(widths[t]):
            out[start + p] = values[order[p]]


@njit(cache=True, error_model="numpy")
def _placed(cells: np.ndarray, values: np.ndarray, out: np.ndarray) -> None:
    for i in range(cells.shape[0]):
        out[cells[i]] = values[i]


@njit(cache=True, error_model="numpy")
def _column_totals(
    extents: np.ndarray, starts: np.ndarray, rank: np.ndarray, values: np.ndarray, out: np.ndarray
) -> None:
    for n in range(extents.shape[0]):  # the tail sums' recurrence, from the last cell
        place, last = rank[n], extents[n] - 1
        if last < 0:
            out[n] = 0.0
            continue
        total = values[starts[last] + place]
        for t in range(last - 1, -1, -1):
            total = values[starts[t] + place] + total
        out[n] = total


class CompiledScans:
    """:class:`~fedhpg.common.staircase.Scans` in numba, for float64 cells on the CPU (None
    elsewhere: the staircase's own torch code runs)."""

    @staticmethod
    def _fits(values: torch.Tensor) -> bool:
        return values.device.type == "cpu" and values.dtype == torch.float64 and values.dim() == 1

    def tail_sums(
        self, layout: Staircase, values: torch.Tensor, scale: torch.Tensor | None
    ) -> torch.Tensor | None:
        if not self._fits(values):
            return None
        out = torch.empty_like(values)
        factors = np.empty(0) if scale is None else scale.numpy()
        _tail_sums(values.contiguous().numpy(), layout.width_array, layout.start_array,
                   factors, out.numpy())  # fmt: skip
        return out

    def cells(self, layout: Staircase) -> tuple[torch.Tensor, torch.Tensor] | None:
        if layout.extents.device.type != "cpu":
            return None
        time = torch.empty(layout.size, dtype=torch.int64)
        column = torch.empty(layout.size, dtype=torch.int64)
        _cells(layout.width_array, layout.start_array, layout.order.numpy(), time.numpy(),
               column.numpy())  # fmt: skip
        return time, column

    def step_powers(self, layout: Staircase, bases: torch.Tensor) -> torch.Tensor | None:
        if not self._fits(bases):
            return None
        out = bases.new_empty(layout.size)
        _step_powers(bases.contiguous().numpy(), layout.width_array, layout.start_array,
                     out.numpy())  # fmt: skip
        return out

    def arrangement(
        self, layout: Staircase
    ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray] | None:
        extents = layout.extents
        if extents.device.type != "cpu" or extents.numel() == 0:
            return None
        order = torch.empty_like(extents)
        rank = torch.empty_like(extents)
        widths = np.empty(int(extents.max()), dtype=np.int64)
        _arrangement(extents.contiguous().numpy(), order.numpy(), rank.numpy(), widths)
        starts = np.zeros_like(widths)
        np.cumsum(widths[:-1], out=starts[1:])
        return order, rank, widths, starts

    def per_cell(self, layout: Staircase, values: torch.Tensor) -> torch.Tensor | None:
        if not self._fits(values):
            return None
        out = torch.empty(layout.size, dtype=values.dtype)
        _per_cell(layout.width_array, layout.start_array, layout.order.numpy(),
                  values.contiguous().numpy(), out.numpy())  # fmt: skip
        return out

    def column_totals(self, layout: Staircase, values: torch.Tensor) -> torch.Tensor | None:
        if not self._fits(values):
            return None
        out = torch.empty(layout.columns, dtype=values.dtype)
        _column_totals(layout.extents.contiguous().numpy(), layout.start_array,
                       layout.rank.numpy(), values.contiguous().numpy(), out.numpy())  # fmt: skip
        return out

    def placed(
        self, layout: Staircase, cells: torch.Tensor, values: torch.Tensor
    ) -> torch.Tensor | None:
        if not (self._fits(values) and cells.device.type == "cpu"):
            return None
        size = layout.size
        # every cell written (each step's own layout): nothing to clear first
        every = len(cells) == size
        out = (torch.empty if every else torch.zeros)(size, dtype=values.dtype)
        _placed(cells.contiguous().numpy(), values.contiguous().numpy(), out.numpy())
        return out

    def cell(
        self, layout: Staircase, time: torch.Tensor, column: torch.Tensor
    ) -> torch.Tensor | None:
        if time.device.type != "cpu":
            return None
        out = torch.empty(time.shape[0], dtype=torch.int64)
        _cell(layout.start_array, layout.rank.numpy(), time.contiguous().numpy(),
              column.contiguous().numpy(), out.numpy())  # fmt: skip
        return out

    def step_group_sums(
        self, layout: Staircase, values: torch.Tensor, groups: torch.Tensor, table: Staircase
    ) -> torch.Tensor | None:
        if not self._fits(values):
            return None
        out = torch.zeros(table.size, dtype=values.dtype)
        _step_group_sums(layout.extents.numpy(), layout.start_array, layout.rank.numpy(),
                         groups.contiguous().numpy(), table.start_array, table.rank.numpy(),
                         values.contiguous().numpy(), out.numpy())  # fmt: skip
        return out

    def per_step_group(
        self, layout: Staircase, values: torch.Tensor, groups: torch.Tensor, table: Staircase
    ) -> torch.Tensor | None:
        if not self._fits(values):
            return None
        out = torch.empty(layout.size, dtype=values.dtype)
        _per_step_group(layout.width_array, layout.start_array, layout.order.numpy(),
                        groups.contiguous().numpy(), table.start_array, table.rank.numpy(),
                        values.contiguous().numpy(), out.numpy())  # fmt: skip
        return out


SCANS = CompiledScans()
