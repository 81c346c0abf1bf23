"""What one agent contributes to a private round's sum, computed the same way wherever it is
computed: by the server from θ_k (central noise), or by the agent before masking.

A contribution is a vector of d + 2 numbers: w·x (the update, clipped, with the agent's share
of the noise where the agents add it), w (the agent's weight in the average) and b − ½ (b = 1
when the update was not clipped, for adaptive clipping, with its share of that count's noise;
centred, so that one agent more or less moves the count by ½: :mod:`.dp`). The round's sum of
contributions gives the average and the clip's next value (:func:`average`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fedhpg.common.privacy import dp
from fedhpg.common.records.types import RoundResult

WEIGHT_UNIT = float(1 << 20)
"""Weighted averages: an agent's weight is its trajectories over this (so w ≤ 1 for any
budget a request may set), which keeps every coordinate within the fixed-point range."""
EXTRA = 2
"""Words after the update's d: the weight and the centred unclipped count."""
CENTRE = 0.5
"""Subtracted from each agent's unclipped indicator b ∈ {0, 1} (added back in the average)."""


@dataclass(frozen=True, kw_only=True)
class RoundPrivacy:
    """What every agent of a private round must know to contribute (sent with ``Train``)."""

    clip: float = 0.0
    """C, the L2 bound of the update (0: no clipping, secure aggregation alone)."""
    noise_std: float = 0.0
    """Each agent's std of the update's noise (distributed noise; 0 otherwise)."""
    count_std: float = 0.0
    """Each agent's std of the unclipped count's noise."""
    bound: float = 1.0e4
    """Each coordinate's range [−bound, bound] (secure aggregation's fixed point)."""
    weighted: bool = False
    """Weight by trajectories (``strategy=weighted``) rather than 1 each."""


def contribution(
    delta: torch.Tensor,
    trajectories: int,
    settings: RoundPrivacy,
    generator: dp.NoiseSource | None = None,
) -> np.ndarray:
    """One agent's d + 2 numbers (float64) for Δ_k = θ_k − θ̃ (``generator``: the agent's
    noise, where it adds a share)."""
    if settings.clip > 0:
        clipped, norms = dp.clip_rows(delta[None], settings.clip)
        update, unclipped = clipped[0].numpy(), float(norms[0] <= settings.clip)
    else:
        update, unclipped = delta.to(torch.float64).numpy(), 1.0
    weight = trajectories / WEIGHT_UNIT if settings.weighted else 1.0
    row = np.empty(update.size + EXTRA)
    row[:-EXTRA] = np.clip(update, -settings.bound, settings.bound) * weight
    row[-2], row[-1] = weight, unclipped - CENTRE
    if generator is not None and settings.noise_std > 0:
        row[:-EXTRA] += dp.gaussian(generator, update.size, settings.noise_std)
        row[-1] += dp.gaussian(generator, 1, settings.count_std)[0]
    return row


def average(total: np.ndarray, denominator: float | None) -> tuple[np.ndarray, float]:
    """From a round's summed contributions: the average update Σ w·x / D (D = ``denominator``,
    the expected weight under DP, else the sum of the weights) and the fraction unclipped,
    Σ(b − ½)/D + ½ (noisy under DP), clamped to [0, 1]."""
    weights = float(total[-2])
    divide = denominator if denominator is not None else weights
    if not divide > 0:
        return np.zeros(total.size - EXTRA), 0.0
    fraction = float(total[-1]) / divide + CENTRE
    return total[:-EXTRA] / divide, min(max(fraction, 0.0), 1.0)


def redacted(result: RoundResult) -> RoundResult:
    """Agents' statistics without what their data decides directly (their training return and
    their algorithm's statistics): under a privacy mode they never leave the agent. Their
    counts and times do (docs/privacy.md says what they may reveal)."""
    return result.with_stats(train_return=[0.0] * len(result), algorithm={})
