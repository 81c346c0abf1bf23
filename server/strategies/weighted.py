"""``weighted``: θ̃ = Σ_k n_k θ_k / Σ_k n_k, with n_k the trajectories agent k sampled."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from fedhpg.common.records.types import RoundResult
from fedhpg.server.strategies import NoParams, Strategy, register_strategy, rows_of


@register_strategy
class Weighted(Strategy[NoParams]):
    """Agents that sampled more trajectories count for more (FedAvg's data weighting)."""

    name = "weighted"

    def averaging(self) -> str:
        return "weighted"

    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        result: RoundResult,
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        # Normalised in float64: counts near float32's range must not overflow to inf/NaN.
        counts = torch.tensor(result.stats.trajectories, dtype=torch.float64)
        if not bool(counts.sum() > 0):
            return rows_of(result).mean(dim=0)
        weights = (counts / counts.sum()).to(torch.float32)
        return (weights.to(self.device) @ rows_of(result).to(self.device)).cpu()
