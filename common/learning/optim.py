"""Gradient-ascent steps on a flat parameter vector: the paper's plain step, and Adam.

Agents use them for local steps (fresh every round); the ``fedadam`` server strategy keeps one
Adam across rounds, whose :meth:`AdamAscent.state` a checkpoint saves.
"""

from __future__ import annotations

import numpy as np
import torch

from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.records.types import SavedState


def _masked(direction: torch.Tensor, active: torch.Tensor | None) -> torch.Tensor:
    """``direction`` with the rows not ``active`` zero."""
    return direction if active is None else _rows_from(direction, 0.0, active)


def _rows_from(new: torch.Tensor, old: torch.Tensor | float, taken: torch.Tensor) -> torch.Tensor:
    """where(taken, new, old) by rows (``old``: rows, or one value), without waiting for the
    device to count the rows."""
    return torch.where(taken.unsqueeze(1), new, old)


class PlainAscent:
    """θ ← θ + η g: the paper's update (Algorithm 1 line 8, Algorithm 2 line 10).

    ``gradient`` is one vector [d], or rows [A, d] of which only the ``active`` ones step."""

    def __init__(self, step_size: float) -> None:
        self.step_size = step_size

    def direction(self, gradient: torch.Tensor, active: torch.Tensor | None = None) -> torch.Tensor:
        return _masked(self.step_size * gradient, active)


class AdamAscent:
    """Adam on the flat parameter vector (ascent).

    Written out rather than taken from ``torch.optim``: the first ``torch.optim`` step imports
    torch's compiler stack (slow, in every process), and this keeps every operation explicit.
    """

    def __init__(
        self, step_size: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ) -> None:
        self.step_size, self.betas, self.eps = step_size, betas, eps
        self.steps = 0
        self.first: torch.Tensor | None = None
        self.second: torch.Tensor | None = None

    def direction(self, gradient: torch.Tensor, active: torch.Tensor | None = None) -> torch.Tensor:
        """The step for ``gradient``: one vector [d], or rows [A, d] (several agents' own
        Adams), of which only the ``active`` ones step and count a step."""
        if gradient.dim() == 2:
            return self._rows(gradient, active)
        beta1, beta2 = self.betas
        if self.first is None or self.second is None:
            self.first, self.second = torch.zeros_like(gradient), torch.zeros_like(gradient)
        self.steps += 1
        self.first = beta1 * self.first + (1 - beta1) * gradient
        self.second = beta2 * self.second + (1 - beta2) * gradient * gradient
        first_hat = self.first / (1 - beta1**self.steps)
        second_hat = self.second / (1 - beta2**self.steps)
        return self.step_size * first_hat / (second_hat.sqrt() + self.eps)

    def _rows(self, gradient: torch.Tensor, active: torch.Tensor | None) -> torch.Tensor:
        beta1, beta2 = self.betas
        if self.first is None or self.second is None:
            self.first, self.second = torch.zeros_like(gradient), torch.zeros_like(gradient)
            self.row_steps = torch.zeros(
                gradient.shape[0], dtype=torch.int64, device=gradient.device
            )
        stepping = (
            torch.ones(gradient.shape[0], dtype=torch.bool, device=gradient.device)
            if active is None
            else active
        )
        self.row_steps = self.row_steps + stepping.long()
        first = beta1 * self.first + (1 - beta1) * gradient
        self.first = _rows_from(first, self.first, stepping)
        second = beta2 * self.second + (1 - beta2) * gradient * gradient
        self.second = _rows_from(second, self.second, stepping)
        steps = self.row_steps.clamp_min(1).double().unsqueeze(-1)
        first_hat = self.first / (1 - beta1**steps).to(gradient.dtype)
        second_hat = self.second / (1 - beta2**steps).to(gradient.dtype)
        return _masked(self.step_size * first_hat / (second_hat.sqrt() + self.eps), stepping)

    def state(self) -> SavedState:
        """The step count and both moments: what :meth:`restore` takes back."""
        if self.first is None or self.second is None:
            return SavedState(scalars={"steps": self.steps})
        # Views, not copies: direction() replaces the moment tensors, never writes into them.
        return SavedState(
            scalars={"steps": self.steps},
            arrays={"first": self.first.numpy(), "second": self.second.numpy()},
        )

    def restore(self, state: SavedState) -> None:
        self.steps = int(state.scalars.get("steps", 0))
        if self.steps:
            self.first = torch.from_numpy(np.array(state.arrays["first"]))
            self.second = torch.from_numpy(np.array(state.arrays["second"]))


Optimizer = PlainAscent | AdamAscent


def make_optimizer(algo: AlgoConfig) -> Optimizer:
    """Gradient *ascent*: plain steps θ += η g (the paper) or Adam, fresh every round."""
    if algo.optimizer == "sgd":
        return PlainAscent(algo.step_size)
    if algo.optimizer == "adam":
        return AdamAscent(algo.step_size)
    raise ValueError(f"algo.optimizer must be 'sgd' or 'adam', got {algo.optimizer!r}")
