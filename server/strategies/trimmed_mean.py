"""``trimmed_mean``: per coordinate, drop the ⌊βm⌋ largest and smallest of the m θ_k
aggregated, average the rest (robust to ⌊βm⌋ attackers among those m rows)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fedhpg.common.configuration.registry import OptionError
from fedhpg.server.strategies import CoordinateRule, by_columns, register_strategy


@dataclass(frozen=True, kw_only=True)
class TrimmedMeanParams:
    trim_fraction: float = 0.2
    """β: the fraction of the aggregated updates trimmed from each end, per coordinate.
    Tolerates ⌊βm⌋ attackers among the m rows of a round (m = K only when every agent takes
    part): ⌊0.2 · 4⌋ = 0, so β = 0.2 over 4 sampled agents tolerates none."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.trim_fraction < 0.5:
            raise OptionError("trim_fraction", f"got {self.trim_fraction!r}, must be in [0, 0.5)")


def trimmed_mean(rows: torch.Tensor, trim_fraction: float) -> torch.Tensor:
    """Mean of each column of [K, d] without its ⌊βK⌋ smallest and largest entries."""
    count = rows.shape[0]
    cut = math.floor(trim_fraction * count)
    if cut == 0:
        return rows.mean(dim=0)
    return rows.sort(dim=0).values[cut : count - cut].mean(dim=0)


@register_strategy
class TrimmedMean(CoordinateRule[TrimmedMeanParams]):
    """Coordinate-wise trimmed mean (Yin et al., 2018)."""

    name = "trimmed_mean"
    Params = TrimmedMeanParams

    def tolerance(self, rows: int) -> int:
        return math.floor(self.params.trim_fraction * rows)

    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        return by_columns(rows, lambda columns: trimmed_mean(columns, self.params.trim_fraction))
