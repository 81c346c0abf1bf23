"""Server-side aggregation (Algorithm 1 line 9, Algorithm 2 line 11)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True, kw_only=True)
class AgentResult:
    """One agent's returned parameter vector and the weight it carries in a weighted mean."""

    agent_index: int
    theta: torch.Tensor
    trajectories: int


def aggregate(results: Sequence[AgentResult], *, rule: str = "uniform") -> torch.Tensor:
    """θ̃ = (1/K) Σ_k θ_k, or the trajectory-weighted mean.

    Results are summed in agent-index order, so the order in which updates arrived over the
    network cannot change a single bit of the result.
    """
    if not results:
        raise ValueError("cannot aggregate zero agent results")
    ordered = sorted(results, key=lambda r: r.agent_index)
    stacked = torch.stack([r.theta for r in ordered])
    if rule == "uniform":
        return stacked.mean(dim=0)
    if rule == "weighted":
        weights = torch.tensor([float(r.trajectories) for r in ordered], dtype=stacked.dtype)
        return (weights / weights.sum()) @ stacked
    raise ValueError(f"aggregation rule must be 'uniform' or 'weighted', got {rule!r}")
