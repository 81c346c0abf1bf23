"""FedPG-BR's Byzantine filter (Fan et al., NeurIPS 2021, Algorithm 1.1) on K gradients.

With V = 2 log(2K/δ) and the variance bound σ (E‖g(τ|θ) − ∇J(θ)‖² ≤ σ²):

rule 1: S = {k : |{k' : ‖μ_k' − μ_k‖ ≤ T}| > K/2},  T = 2σ √(V / B_t);
        the reference μ_ref is the member of S nearest to the mean of S;
        G = {k : ‖μ_k − μ_ref‖ ≤ T}.
rule 2: where rule 1 keeps fewer than (1 − α)K (or S is empty), the same with T = 2σ, the
        bound that holds without the concentration over B_t.
μ_t = mean of G (nothing, where rule 2 finds no majority either).

The thresholds are those FedPG-BR's released code applies (its figures come from them): the
paper prints 2T for G under rule 1 and 4σ for rule 2's majority. σ is an option; where it is
not given, it is estimated from the round's gradients themselves (a departure from the paper,
which assumes σ known), see :func:`estimated_sigma`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class FilterResult:
    kept: list[int]
    """Row indices of the gradients kept, ascending (empty where neither rule found a
    majority)."""
    rule: int
    """1 or 2: the rule that decided; 0 where none did."""
    threshold: float
    """The distance the deciding rule used (rule 2's where none did)."""
    sigma: float
    """The σ the thresholds came from."""


def estimated_sigma(gradients: torch.Tensor, batch_size: int) -> float:
    """σ̂ from K gradients of B_t trajectories each, robust to fewer than K/2 outliers.

    Two honest gradients differ by ‖μ_i − μ_j‖² ≈ 2σ²/B_t on average. Each gradient's distance
    to its ⌊K/2⌋-th nearest other gradient is, for an honest one, a distance to another honest
    one while more than half are honest; the median of those over the K rows is one of an
    honest row, so σ̂ = √(B_t / 2) · that median.
    """
    count = gradients.shape[0]
    if count < 2:
        return 0.0
    distances = torch.cdist(gradients.double(), gradients.double())
    nearest = distances.sort(dim=1).values[:, max(count // 2, 1)]  # column 0 is the row itself
    return float(nearest.median()) * math.sqrt(batch_size / 2)


def _majority_filter(distances: torch.Tensor, gradients: torch.Tensor, threshold: float) -> list[int]:
    count = distances.shape[0]
    members = ((distances <= threshold).sum(dim=1) > count / 2).nonzero().flatten()
    if members.numel() == 0:
        return []
    centre = gradients[members].mean(dim=0)
    reference = members[(gradients[members] - centre).norm(dim=1).argmin()]
    return (distances[reference] <= threshold).nonzero().flatten().tolist()


def byzantine_filter(
    gradients: torch.Tensor,
    *,
    batch_size: int,
    sigma: float | None,
    delta: float,
    alpha: float,
) -> FilterResult:
    """Which of the [K, d] ``gradients`` (each from ``batch_size`` trajectories) to average."""
    count = gradients.shape[0]
    rows = gradients.double()
    sigma = estimated_sigma(rows, batch_size) if sigma is None else sigma
    distances = torch.cdist(rows, rows)
    variance_factor = 2 * math.log(2 * count / delta)
    first = 2 * sigma * math.sqrt(variance_factor / batch_size)
    kept = _majority_filter(distances, rows, first)
    if kept and len(kept) >= (1 - alpha) * count:
        return FilterResult(kept=kept, rule=1, threshold=first, sigma=sigma)
    second = 2 * sigma
    kept = _majority_filter(distances, rows, second)
    return FilterResult(kept=kept, rule=2 if kept else 0, threshold=second, sigma=sigma)
