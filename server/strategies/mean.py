"""``mean``: θ̃ = (1/K) Σ_k θ_k (Algorithm 1 line 9, Algorithm 2 line 11)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from fedhpg.common.types import AgentUpdate
from fedhpg.server.strategies import NoParams, Strategy, register_strategy, stacked


@register_strategy
class Mean(Strategy[NoParams]):
    """The paper's server: the plain average of the returned parameter vectors."""

    name = "mean"

    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        results: Sequence[AgentUpdate],
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        return stacked(results).mean(dim=0)
