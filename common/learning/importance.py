"""Importance weights w = p(τ|θ_0) / p(τ|θ_n) for FedHPGVR, computed in log space.

The environment's transition probabilities appear in both densities and cancel, so only the
policies' log-probabilities of the taken actions are needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fedhpg.common.learning.staircase import ordered_sums


def log_ratio_steps(
    snapshot_log_probs: torch.Tensor, current_log_probs: torch.Tensor, alive: torch.Tensor
) -> torch.Tensor:
    """log π_0(a_t|s_t) − log π_n(a_t|s_t) on alive steps, 0 elsewhere; [T, B] float64."""
    difference = snapshot_log_probs.double() - current_log_probs.double()
    return torch.where(alive, difference, torch.zeros_like(difference))


def trajectory_weights(log_ratios: torch.Tensor) -> torch.Tensor:
    """w(τ) = Π_t π_0/π_n over the whole trajectory; [B]."""
    return log_ratios.sum(dim=0).exp()


def per_decision_weights(log_ratios: torch.Tensor) -> torch.Tensor:
    """w_{0:h} = Π_{t ≤ h} π_0/π_n, the weight of the reward at step h; [T, B]."""
    return log_ratios.cumsum(dim=0).exp()


@dataclass(frozen=True, kw_only=True)
class WeightStats:
    mean: float
    max: float
    clipped_fraction: float


def clip_weights(
    weights: torch.Tensor, bounds: list[float] | None, counted: torch.Tensor | None = None
) -> tuple[torch.Tensor, float]:
    """Clip to [lo, hi]; returns the clipped weights and the fraction of ``counted`` entries
    (all by default; the alive steps for per-decision weights) that the clip changed."""
    if bounds is None:
        return weights, 0.0
    low, high = bounds
    clipped = weights.clamp(min=low, max=high)
    changed = clipped != weights
    if counted is not None:
        return clipped, float(changed[counted].double().mean()) if counted.any() else 0.0
    return clipped, float(changed.double().mean())


def self_normalise(weights: torch.Tensor, groups: torch.Tensor | None = None) -> torch.Tensor:
    """Rescale so the weights average to 1 across the batch (per step for [T, B] weights), or
    across each agent's own columns where ``groups`` [B] says whose each column is.

    Used in a batch mean (1/b) Σ_j w_j g_j, this turns it into Σ_j w_j g_j / Σ_j w_j.
    """
    tiny = torch.finfo(weights.dtype).tiny
    if groups is None:
        total = weights.sum(dim=-1, keepdim=True)
        return weights * weights.shape[-1] / total.clamp_min(tiny)
    size = int(groups.max()) + 1
    totals = ordered_sums(groups, weights.movedim(-1, 0), size).movedim(0, -1)
    counts = torch.bincount(groups, minlength=size).to(weights.dtype)
    return weights * counts[groups] / totals.index_select(-1, groups).clamp_min(tiny)
