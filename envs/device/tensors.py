"""What every torch family shares: a table of its variants' constants, and copies whose state is
one tensor per quantity, stepped as elementwise arithmetic.

A family writes three functions of its own (:meth:`TensorCopies.start`,
:meth:`TensorCopies.advance`, :meth:`TensorCopies.observe`) over a [state_size, M] state and
per-copy constants ``p`` (name -> [M]); :class:`TensorCopies` does the bookkeeping: which copies
a call touches, step counts, truncation at each copy's step limit.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import torch

from fedhpg.envs.device.protocols import CopyStep, ResetStream
from fedhpg.envs.tensor_writes import put_distinct

Params = dict[str, torch.Tensor]


class TensorCopies(abc.ABC):
    """M copies: state [state_size, M], each copy's constants ``params`` (name -> [M]), its
    step limit ``limit`` [M] and shared ``tables`` (name -> [V, ...], indexed by a copy's
    ``params["table"]`` where a family has tables)."""

    state_size: ClassVar[int]
    state_dtype: ClassVar[torch.dtype] = torch.float32
    reset_draws: ClassVar[int] = 0
    """Uniforms a copy's reset takes from its stream."""
    step_noise: int = 0
    """Uniforms a copy's step takes (0: deterministic steps)."""
    truncate_terminated: ClassVar[bool] = True
    """Whether a step that terminates at the step limit also reports truncation (gymnasium's
    ``TimeLimit`` does; GridWorld's own limit does not)."""

    def __init__(self, params: Params, limit: torch.Tensor, tables: Mapping[str, torch.Tensor]):
        self.params = params
        self.limit = limit
        self.tables = dict(tables)
        self.device = limit.device
        self.num_copies = int(limit.shape[0])
        self.state = torch.zeros(
            self.state_size, self.num_copies, dtype=self.state_dtype, device=self.device
        )
        self.steps = torch.zeros(self.num_copies, dtype=torch.int64, device=self.device)

    @abc.abstractmethod
    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        """First states [state_size, m] from ``uniforms`` [m, reset_draws] float64."""

    @abc.abstractmethod
    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(next state, reward float64, terminated, success) of one step of m copies."""

    @abc.abstractmethod
    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        """Observations [m, ...] of states [state_size, m]."""

    def _params(self, columns: torch.Tensor | None) -> Params:
        if columns is None:
            return self.params
        return {name: values[columns] for name, values in self.params.items()}

    def reset(self, columns: torch.Tensor, stream: ResetStream) -> torch.Tensor:
        p = self._params(columns)
        count = int(columns.shape[0])
        draws = (
            stream.uniforms(self.reset_draws).to(self.device)
            if self.reset_draws
            else torch.zeros((count, 0), dtype=torch.float64, device=self.device)
        )
        state = self.start(draws, p).to(self.state_dtype)
        put_distinct(self.state, (slice(None), columns), state)
        put_distinct(self.steps, columns, 0)
        return self.observe(state, p)

    def keep(self, columns: torch.Tensor) -> None:
        """Keep only the copies ``columns`` (increasing), in that order: they become copies
        0 … m − 1 (an end check's narrowing of the batch to the copies that still run)."""
        self.params = self._params(columns)
        self.limit = self.limit[columns]
        self.state = self.state[:, columns]
        self.steps = self.steps[columns]
        self.num_copies = int(columns.shape[0])

    def step(
        self, actions: torch.Tensor, columns: torch.Tensor | None, noise: torch.Tensor | None
    ) -> CopyStep:
        p = self._params(columns)
        if columns is None:
            state, steps = self.state, self.steps + 1
        else:
            state, steps = self.state[:, columns], self.steps[columns] + 1
        state, reward, terminated, success = self.advance(state, actions, p, noise)
        limit = self.limit if columns is None else self.limit[columns]
        if columns is None:
            self.state, self.steps = state, steps
        else:
            put_distinct(self.state, (slice(None), columns), state)
            put_distinct(self.steps, columns, steps)
        truncated = steps >= limit
        if not self.truncate_terminated:
            truncated &= ~terminated
        return CopyStep(
            obs=self.observe(state, p),
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            success=success,
        )


class TableFamily:
    """Variants' constants as [V] (or [V, n]) tensors on a device (one row per variant it was
    made of)."""

    def __init__(
        self,
        copies_class: type[TensorCopies],
        constants: Mapping[str, Sequence[float] | Sequence[int] | Sequence[Sequence[float]]],
        limits: Sequence[int],
        device: torch.device,
        *,
        dtypes: Mapping[str, torch.dtype] | None = None,
        tables: Mapping[str, torch.Tensor] | None = None,
    ) -> None:
        self.copies_class = copies_class
        self.device = device
        self.step_noise = copies_class.step_noise
        kinds = dict(dtypes or {})
        self.constants = {
            name: torch.tensor(list(values), dtype=kinds.get(name, torch.float32)).to(device)
            for name, values in constants.items()
        }
        self.limits = torch.tensor(list(limits), dtype=torch.int64).to(device)
        self.tables = {name: table.to(device) for name, table in (tables or {}).items()}

    def copies(self, rows: torch.Tensor, counts: torch.Tensor) -> TensorCopies:
        each = torch.repeat_interleave(rows.to(self.device), counts.to(self.device))
        return self.copies_class(
            {name: values[each] for name, values in self.constants.items()},
            self.limits[each],
            self.tables,
        )


def physics_family(
    copies_class: type[TensorCopies],
    variants: Sequence[Any],
    physics_of: Callable[[Any], Mapping[str, float] | None],
    names: Sequence[str],
    step_limit: int,
    device: torch.device,
) -> TableFamily | None:
    """The family of variants that each carry the constants ``names`` (``physics_of(v)``; None
    where a variant is not one ``copies_class`` models, and then None for all), each with its
    step limit (``step_limit`` where the variant names none)."""
    physics = [physics_of(v) for v in variants]
    if any(p is None for p in physics):
        return None
    constants = {name: [p[name] for p in physics if p is not None] for name in names}
    limits = [int(getattr(v, "step_limit", 0) or step_limit) for v in variants]
    return TableFamily(copies_class, constants, limits, device)
