"""``median``: θ̃ = the coordinate-wise median of the θ_k aggregated (robust while fewer than
half of those rows are attackers: ⌈m/2⌉ − 1 of m)."""

from __future__ import annotations

import torch

from fedhpg.server.strategies import CoordinateRule, NoParams, by_columns, register_strategy


def coordinate_median(rows: torch.Tensor) -> torch.Tensor:
    """Per column of [K, d]: the middle value (the mean of the two middle ones for even K)."""
    ordered = rows.sort(dim=0).values
    count = rows.shape[0]
    middle = count // 2
    if count % 2:
        return ordered[middle]
    return (ordered[middle - 1] + ordered[middle]) / 2


@register_strategy
class Median(CoordinateRule[NoParams]):
    """Coordinate-wise median (Yin et al., 2018): any coordinate stays between honest values
    while attackers are fewer than half of the aggregated rows."""

    name = "median"

    def tolerance(self, rows: int) -> int:
        return (rows - 1) // 2

    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        return by_columns(rows, coordinate_median)
