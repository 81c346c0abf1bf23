"""Agent-level differential privacy of an averaged update (DP-FedAvg, McMahan et al. 2018).

Each selected agent's update Δ_k = θ_k − θ̃ is clipped to L2 norm C; the sum of the clipped
updates has sensitivity C to adding or removing one agent, so Gaussian noise N(0, σ²C²·I) on
the sum makes each round a Gaussian mechanism of noise multiplier σ. Central noise is drawn by
the server once; distributed noise is drawn by every agent, N(0, σ²C²/m_min) each, so that the
sum of at least m_min agents' noise has variance σ²C² (secure aggregation then hides each
agent's part). The average divides by the expected number of participants, a public constant,
so that the denominator leaks nothing.

Adaptive clipping (Andrew et al. 2021, "Differentially private learning with adaptive
clipping"): C follows a target quantile γ of the update norms by a geometric step on the noisy
fraction of unclipped updates, C ← C·exp(−η(b̄ − γ)); that count's noise (σ_b) is part of the
same release, so the update's own noise multiplier is raised to keep the total at σ.
"""

from __future__ import annotations

import math
import secrets
from collections.abc import Sequence

import numpy as np
import torch


def clip_rows(deltas: torch.Tensor, bound: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Each row of ``deltas`` [m, d] scaled to L2 norm at most ``bound``; (the clipped rows in
    float64, the rows' norms before clipping)."""
    rows = deltas.to(torch.float64)
    norms = torch.linalg.vector_norm(rows, dim=1)
    factors = torch.clamp(bound / torch.clamp(norms, min=1e-300), max=1.0)
    return rows * factors[:, None], norms


def noise_generator(seed: Sequence[int] | None = None) -> np.random.Generator:
    """The generator of DP noise: from the operating system's entropy unless ``seed`` is given
    (a seeded noise is known to whoever knows the seed, so it protects nothing: tests and
    reproducible experiments only; e.g. (noise seed, round, agent))."""
    entropy = secrets.randbits(128) if seed is None else list(seed)
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy)))


SERVER_STREAM = 0x5EC0DE
"""Tags the server's seeded noise stream apart from every agent's."""


def noise_stream(seed: int | None, round_index: int, agent: int | None) -> np.random.Generator:
    """The DP noise of ``agent`` (None: the server) in a round: unpredictable unless the run
    sets ``privacy.noise_seed``, then (seed, round, agent)'s, the same in every placement."""
    if seed is None:
        return noise_generator()
    return noise_generator((seed, round_index, SERVER_STREAM if agent is None else agent))


def gaussian(generator: np.random.Generator, size: int, std: float) -> np.ndarray:
    """``size`` draws of N(0, std²) in float64."""
    return generator.normal(0.0, std, size) if std > 0 else np.zeros(size)


def per_agent_std(total_std: float, min_agents: int) -> float:
    """The std each of at least ``min_agents`` agents adds so that their sum's is ``total_std``."""
    return total_std / math.sqrt(min_agents)


def update_noise_multiplier(noise_multiplier: float, count_std: float | None) -> float:
    """The noise multiplier of the clipped sum when the unclipped count is released beside it
    with std ``count_std`` (its sensitivity is 1, the sum's C): the two together are a Gaussian
    mechanism of ``noise_multiplier`` iff σ_Δ^−2 + (2σ_b)^−2 = σ^−2 (Andrew et al. 2021, Thm 1).
    None: fixed clipping, σ_Δ = σ."""
    if count_std is None:
        return noise_multiplier
    rest = noise_multiplier**-2 - (2.0 * count_std) ** -2
    if rest <= 0:
        raise ValueError(
            f"the count's noise (std {count_std:g}) alone spends more than noise multiplier "
            f"{noise_multiplier:g} allows; it must be above σ/2 = {noise_multiplier / 2:g}"
        )
    return rest**-0.5


def next_clip(clip: float, unclipped_fraction: float, target_quantile: float, rate: float) -> float:
    """One geometric step of adaptive clipping: C·exp(−η(b̄ − γ)), b̄ the (noisy) fraction of
    updates whose norm was at most C."""
    return clip * math.exp(-rate * (unclipped_fraction - target_quantile))
