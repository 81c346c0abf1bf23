"""``mean``: θ̃ = (1/K) Σ_k θ_k (Algorithm 1 line 9, Algorithm 2 line 11)."""

from __future__ import annotations

import torch

from fedhpg.server.strategies import CoordinateRule, NoParams, register_strategy


@register_strategy
class Mean(CoordinateRule[NoParams]):
    """The paper's server: the plain average of the returned parameter vectors."""

    name = "mean"

    def averaging(self) -> str:
        return "uniform"

    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        return rows.mean(dim=0)
