"""The trajectories of many agents' rows in one time-major batch.

Column n is one trajectory of row ``owner[n]`` (a row is one agent of the batch); every row's
columns are contiguous. Steps are padded to the longest trajectory T: ``alive[t, n]`` says
whether step t of trajectory n happened, and everything at a dead step is padding (reward 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Trajectories:
    obs: torch.Tensor
    """[T, N, *obs_shape]."""
    actions: torch.Tensor
    """[T, N, *act_shape]: the raw sample the policy drew (before any clipping by the env)."""
    rewards: torch.Tensor
    """[T, N] float64."""
    alive: torch.Tensor
    """[T, N] bool."""
    success: torch.Tensor
    """[N] bool: the episode ended in the task's goal."""
    owner: torch.Tensor
    """[N] int64: the row each trajectory belongs to."""
    counts: torch.Tensor
    """[A] int64: trajectories per row (0 for a row that sampled none)."""

    @property
    def num_rows(self) -> int:
        return int(self.counts.shape[0])

    def steps_per_row(self) -> torch.Tensor:
        """Alive steps of each row, [A] int64."""
        per_column = self.alive.sum(dim=0)
        return torch.zeros_like(self.counts).index_add_(0, self.owner, per_column)

    def returns(self, gammas: torch.Tensor | None = None) -> torch.Tensor:
        """Each trajectory's return Σ_t γ^t r_t, [N] float64 (undiscounted without
        ``gammas``, else each column discounted by its row's γ, ``gammas`` [A])."""
        if gammas is None:
            return self.rewards.sum(dim=0)
        steps = torch.arange(self.rewards.shape[0], dtype=torch.float64, device=gammas.device)
        discounts = gammas.double()[self.owner].unsqueeze(0) ** steps.unsqueeze(1)
        return (discounts * self.rewards).sum(dim=0)

    def per_row(self, values: torch.Tensor) -> torch.Tensor:
        """Sum of a per-trajectory [N] quantity over each row's trajectories, [A]."""
        return values.new_zeros(self.num_rows).index_add_(0, self.owner, values)

    def lengths(self) -> torch.Tensor:
        """Each trajectory's alive steps, [N]."""
        return self.alive.sum(dim=0)
