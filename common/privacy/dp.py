"""Agent-level differential privacy of an averaged update (DP-FedAvg, McMahan et al. 2018).

Each selected agent's update Δ_k = θ_k − θ̃ is clipped to L2 norm C; the sum of the clipped
updates has sensitivity C to adding or removing one agent (2C to replacing one), so Gaussian
noise N(0, σ²C²·I) on the sum makes each round a Gaussian mechanism of noise multiplier σ.
Central noise is drawn by the server once; distributed noise is drawn by every agent,
N(0, σ²C²/m_min) each, so that the sum of at least m_min agents' noise has variance σ²C²
(secure aggregation then hides each agent's part). The average divides by the expected number
of participants, a public constant, so that the denominator leaks nothing.

Adaptive clipping (Andrew et al. 2021, "Differentially private learning with adaptive
clipping"): C follows a target quantile γ of the update norms by a geometric step on the noisy
fraction of unclipped updates, C ← C·exp(−η(b̄ − γ)). Each agent contributes its indicator
centred, b − ½ (b = 1 when its update was not clipped), as TF-Privacy's quantile estimator
does: the count's sensitivity is then ½ to adding or removing one agent (1 to replacing one)
instead of 1. Its noise (σ_b) is part of the same release, so the update's own noise
multiplier is raised to keep the total at σ (:func:`update_noise_multiplier`).

Unseeded noise comes from the operating system's CSPRNG, each draw a sum of Gaussians
(:class:`SecureNoise`); seeded noise (``privacy.noise_seed``) from numpy's PCG64, reproducible
and known to whoever knows the seed.
"""

from __future__ import annotations

import math
import os
import secrets
from collections.abc import Sequence
from typing import TypeAlias

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
    """A numpy generator of DP noise: from the operating system's entropy unless ``seed`` is
    given (a seeded noise is known to whoever knows the seed, so it protects nothing: tests and
    reproducible experiments only; e.g. (noise seed, round, agent))."""
    entropy = secrets.randbits(128) if seed is None else list(seed)
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy)))


class SecureNoise:
    """Gaussian noise for a DP release, as Opacus's ``secure_mode`` draws it: its bits from the
    operating system's CSPRNG (``os.urandom``), and each draw the sum of ``SUMMANDS`` standard
    normals over √SUMMANDS (Holohan and Braghin 2021, "Secure random sampling in differential
    privacy"), which blurs the gaps a single floating-point Gaussian leaves between the values
    it can take (Mironov 2012's attack on floating-point noise). The normals are Box–Muller's
    (both of each pair) from 53-bit uniforms. Nothing is seeded: no two draws repeat."""

    SUMMANDS = 4

    def normal(self, loc: float, scale: float, size: int) -> np.ndarray:
        """``size`` draws of N(loc, scale²) in float64 (numpy's ``Generator.normal``)."""
        normals = standard_normals(self.SUMMANDS * size).reshape(self.SUMMANDS, size)
        return loc + scale * (normals.sum(axis=0) / math.sqrt(self.SUMMANDS))


def standard_normals(count: int) -> np.ndarray:
    """``count`` N(0, 1) draws by Box–Muller from ``os.urandom``'s bits: each pair of 64-bit
    words gives two 53-bit uniforms u, v in [0, 1) and the normals √(−2 ln(1 − u))·cos(2πv),
    √(−2 ln(1 − u))·sin(2πv), in that order."""
    pairs = (count + 1) // 2
    words = np.frombuffer(os.urandom(16 * pairs), dtype=np.uint64) >> np.uint64(11)
    uniform = words.astype(np.float64) * 2.0**-53
    radius = np.sqrt(-2.0 * np.log1p(-uniform[0::2]))
    angle = (2.0 * np.pi) * uniform[1::2]
    normals = np.empty(2 * pairs)
    normals[0::2] = radius * np.cos(angle)
    normals[1::2] = radius * np.sin(angle)
    return normals[:count]


NoiseSource: TypeAlias = np.random.Generator | SecureNoise
"""Where a release's Gaussian noise comes from (both have numpy's ``normal``)."""

SERVER_STREAM = 0x5EC0DE
"""Tags the server's seeded noise stream apart from every agent's."""


def noise_stream(
    seed: int | None, round_index: int, agent: int | None, *, secure: bool = True
) -> NoiseSource:
    """The DP noise of ``agent`` (None: the server) in a round: unpredictable unless the run
    sets ``privacy.noise_seed``, then (seed, round, agent)'s, the same in every placement.
    Unseeded: the operating system's CSPRNG as :class:`SecureNoise` (``secure``, the default
    of ``privacy.secure_noise``), else numpy's PCG64 seeded from it."""
    if seed is not None:
        return noise_generator((seed, round_index, SERVER_STREAM if agent is None else agent))
    return SecureNoise() if secure else noise_generator()


def gaussian(generator: NoiseSource, size: int, std: float) -> np.ndarray:
    """``size`` draws of N(0, std²) in float64."""
    return generator.normal(0.0, std, size) if std > 0 else np.zeros(size)


def per_agent_std(total_std: float, min_agents: int) -> float:
    """The std each of at least ``min_agents`` agents adds so that their sum's is ``total_std``."""
    return total_std / math.sqrt(min_agents)


def update_noise_multiplier(noise_multiplier: float, count_std: float | None) -> float:
    """σ_Δ, the noise multiplier of the clipped sum when the centred count Σ(b − ½) is
    released beside it with noise std σ_b = ``count_std``, such that the two together are one
    Gaussian mechanism of multiplier σ = ``noise_multiplier`` (Andrew et al. 2021, Thm 1).
    None: fixed clipping, σ_Δ = σ.

    A Gaussian mechanism releasing f with std s_i on coordinate i is, for a pair of
    neighbouring inputs, the Gaussian mechanism of sensitivity ‖(f − f′)/s‖₂ and std 1; the
    accountant composes multiplier σ for sensitivity C (adding or removing one agent) or σ/2
    for 2C (replacing one, with sampling without replacement). The sum moves by at most C, the
    centred count by ½ (adding or removing one agent), or 2C and 1 (replacing one: b − ½ goes
    from −½ to ½), so the release's worst ‖·/s‖² is

    - add or remove one: (C/(σ_Δ C))² + (½/σ_b)² = σ_Δ⁻² + (2σ_b)⁻², which must be σ⁻²;
    - replace one: (2C/(σ_Δ C))² + (1/σ_b)² = 4(σ_Δ⁻² + (2σ_b)⁻²), which must be (2/σ)².

    Both give σ_Δ⁻² = σ⁻² − (2σ_b)⁻² (tests/test_privacy_maths.py measures both from the
    contributions themselves). An uncentred b ∈ {0, 1} would move the count by 1 when one agent
    is added: σ_Δ⁻² + σ_b⁻² = σ⁻², a larger σ_Δ than this one."""
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
    updates whose norm was at most C, clamped to [0, 1] (noise can take it outside; a fraction
    outside would step further than any true one could)."""
    fraction = min(max(unclipped_fraction, 0.0), 1.0)
    return clip * math.exp(-rate * (fraction - target_quantile))
