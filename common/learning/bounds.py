"""The constants of Theorem 1 estimated from an agent's own trajectories, and the four terms of
the bound (eq. 7) they give. Pure maths: no wire, no processes.

From one batch of B per-trajectory gradients g_b = g(l_b | θ) (eq. 5 or 6), two sums are
enough: S = Σ_b g_b (B times the batch gradient the agent computes anyway) and Q = Σ_b ‖g_b‖².
With i.i.d. trajectories (the paper's estimators without a baseline, or with a constant one):

- σ̂² = (Q − ‖S‖²/B) / (B − 1) is unbiased for σ² = E‖g − ∇J_k‖² (Assumption 1 at θ);
- M̂ = Q / B is unbiased for M = E‖g‖² (Assumption 3 at θ);
- ‖S/B‖² − σ̂²/B is unbiased for ‖∇J_k(θ)‖² (E‖ḡ‖² = ‖∇J_k‖² + σ²/B).

With the leave-one-out mean baseline the g_b of one batch are not independent (each uses the
others' rewards): the same formulas then measure the spread of the batch's own terms, which is
what a batch of that size delivers, but are no longer exactly unbiased for Assumption 1's σ².

The assumptions ask for suprema over every policy; these are estimates at the θ the agent
sampled at, so a bound made from them is a local estimate of the worst case, not a guarantee.

L (Assumption 4) is estimated from the federation's gradient estimates at successive θ̃:
‖∇J(θ̃_t) − ∇J(θ̃_{t−1})‖² is estimated without bias by ‖ĝ_t − ĝ_{t−1}‖² minus the two
estimates' variances (independent batches), and the secant L̂ = √(that) / ‖θ̃_t − θ̃_{t−1}‖ is a
lower estimate of the true L (a secant never exceeds the largest curvature on its segment).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch


@dataclass(frozen=True)
class GradientMoments:
    """One batch's estimates (see the module docstring); batch must be ≥ 2 for a variance."""

    batch: int
    variance: float
    """σ̂², the per-trajectory gradient variance (trace of the covariance)."""
    second_moment: float
    """M̂ = E‖g‖²."""
    grad_norm_sq: float
    """Unbiased ‖∇J_k‖² (may be slightly negative for a noisy batch, as unbiased estimates are)."""


def moments_from_sums(total: torch.Tensor, sum_sq_norms: float, batch: int) -> GradientMoments:
    """From S = Σ_b g_b and Q = Σ_b ‖g_b‖² of ``batch`` trajectories, in float64."""
    if batch < 2:
        raise ValueError(f"a variance needs at least 2 trajectories, got {batch}")
    square_of_sum = float(total.to(torch.float64).square().sum())
    variance = max((sum_sq_norms - square_of_sum / batch) / (batch - 1), 0.0)
    return GradientMoments(
        batch=batch,
        variance=variance,
        second_moment=sum_sq_norms / batch,
        grad_norm_sq=square_of_sum / batch**2 - variance / batch,
    )


def gradient_moments(per_trajectory: torch.Tensor) -> GradientMoments:
    """From the [B, d] matrix of per-trajectory gradients."""
    rows = per_trajectory.to(torch.float64)
    return moments_from_sums(rows.sum(dim=0), float(rows.square().sum()), rows.shape[0])


def secant_smoothness(
    theta_before: torch.Tensor,
    theta_after: torch.Tensor,
    gradient_before: torch.Tensor,
    gradient_after: torch.Tensor,
    noise_before: float,
    noise_after: float,
) -> float | None:
    """L̂ from two gradient estimates at two points; ``noise_*`` is each estimate's variance
    (σ̂²/B for one agent's batch mean, Σ_k σ̂_k²/(K² B_k) for the federation's mean). None when
    the points coincide."""
    step = float((theta_after - theta_before).to(torch.float64).norm())
    if step == 0.0:
        return None
    difference = float((gradient_after - gradient_before).to(torch.float64).square().sum())
    return max(difference - noise_before - noise_after, 0.0) ** 0.5 / step


@dataclass(frozen=True)
class Theorem1Terms:
    """The four terms of eq. 7 and their sum; ``step_size_ok`` is the theorem's condition
    γ < min(1/L, 2(K + τ̄)/(L K α_B))."""

    optimisation: float
    """2 (J(θ*) − J(θ_0)) / (γ τ̄ T): shrinks with the number of rounds."""
    local_drift: float
    """γ² L² V / (6 K τ̄) Σ_k σ_k² τ_k (τ_k − 1)(2τ_k − 1) / B_k."""
    variance: float
    """γ L V / (K τ̄) Σ_k τ_k² σ_k² / B_k."""
    heterogeneity: float
    """γ L M / τ̄ · (γ L α_A + (1 − γ L / 2) α_B)."""
    step_size_ok: bool

    @property
    def total(self) -> float:
        return self.optimisation + self.local_drift + self.variance + self.heterogeneity


def theorem1_terms(
    *,
    gap: float,
    step_size: float,
    smoothness: float,
    second_moment: float,
    variances: Sequence[float],
    local_iters: Sequence[int],
    batch_sizes: Sequence[int],
    rounds: int,
    v: float = 1.0,
) -> Theorem1Terms:
    """Eq. 7 for K agents. Where the paper leaves a symbol undefined this reads it so:

    - τ̄ is the agents' mean local iteration count (1/K) Σ_k τ_k;
    - V is not defined in the paper; it multiplies both variance terms, default 1;
    - the first term's numerator "2E J(θ*) − J(θ_0)" is read as 2 (J(θ*) − J(θ_0)), the usual
      form, with ``gap`` = J(θ*) − J(θ_0) supplied by the caller (e.g. the largest return the
      environment allows minus the return at θ_0);
    - M is one constant for all agents (Assumption 3): the largest agent's estimate.
    """
    k = len(local_iters)
    if not (k == len(variances) == len(batch_sizes)) or k == 0:
        raise ValueError("variances, local_iters and batch_sizes need one entry per agent")
    if rounds < 1 or step_size <= 0:
        raise ValueError("rounds must be ≥ 1 and the step size > 0")
    tau_bar = sum(local_iters) / k
    alpha_a = sum(t * (t - 1) * (2 * t - 1) for t in local_iters) / (6 * k)
    alpha_b = sum(t * (t - 1) for t in local_iters) / k
    gl = step_size * smoothness
    drift = sum(
        s * t * (t - 1) * (2 * t - 1) / b
        for s, t, b in zip(variances, local_iters, batch_sizes, strict=True)
    )
    spread = sum(t * t * s / b for s, t, b in zip(variances, local_iters, batch_sizes, strict=True))
    limit = 1.0 / smoothness if smoothness > 0 else float("inf")
    if alpha_b > 0 and smoothness > 0:
        limit = min(limit, 2 * (k + tau_bar) / (smoothness * k * alpha_b))
    return Theorem1Terms(
        optimisation=2 * gap / (step_size * tau_bar * rounds),
        local_drift=gl * gl * v / (6 * k * tau_bar) * drift,
        variance=gl * v / (k * tau_bar) * spread,
        heterogeneity=gl * second_moment / tau_bar * (gl * alpha_a + (1 - gl / 2) * alpha_b),
        step_size_ok=step_size < limit,
    )


def bound_stats(moments: GradientMoments) -> dict[str, float]:
    """The names under which an agent reports :class:`GradientMoments` (``algorithm`` stats)."""
    return {
        "bound_variance": moments.variance,
        "bound_second_moment": moments.second_moment,
        "bound_grad_norm_sq": moments.grad_norm_sq,
    }


class SmoothnessProbe:
    """``bound_smoothness``: L̂ from an agent's first two local iterations, the noise-corrected
    secant between its (unclipped) batch gradients at θ̃ and one step on
    (:func:`fedhpg.common.learning.bounds.secant_smoothness`); nothing with one local iteration."""

    def __init__(self) -> None:
        self.points: list[tuple[torch.Tensor, torch.Tensor, float]] = []

    def add(self, theta: torch.Tensor, gradient: torch.Tensor, noise: float) -> None:
        self.points.append((theta.detach().clone(), gradient.detach().clone(), noise))

    def stats(self) -> dict[str, float]:
        if len(self.points) < 2:
            return {}
        (theta0, g0, n0), (theta1, g1, n1) = self.points[:2]
        smoothness = secant_smoothness(theta0, theta1, g0, g1, n0, n1)
        return {} if smoothness is None else {"bound_smoothness": smoothness}


class RowBounds:
    """``algo.bound_estimates`` for rows of agents: each row's moments at θ̃ (its first batch)
    and L̂ from the secant between its first two batch gradients (unclipped)."""

    NAMES = ("bound_variance", "bound_second_moment", "bound_grad_norm_sq", "bound_smoothness")

    def __init__(self, rows: int) -> None:
        self.values = {
            name: torch.full((rows,), float("nan"), dtype=torch.float64) for name in self.NAMES
        }
        self.points: dict[int, list[tuple[torch.Tensor, torch.Tensor, float]]] = {}

    def measure(
        self, rows: Any, theta: torch.Tensor, batch: Any, gradient: torch.Tensor, *, first: bool
    ) -> None:
        """Per-trajectory gradients of ``batch`` at ``theta`` (``rows``: the round): the
        moments of a first batch, a point of each row's secant."""
        with rows.untimed():  # a diagnostic, not the device's work
            per_trajectory = rows.trajectory_gradients(theta, batch, rows.coefficients(batch))
            owner = batch.owner
            for row in torch.nonzero(batch.counts >= 2).squeeze(1).tolist():
                moments = gradient_moments(per_trajectory[owner == row].cpu())
                if first:
                    self.values["bound_variance"][row] = moments.variance
                    self.values["bound_second_moment"][row] = moments.second_moment
                    self.values["bound_grad_norm_sq"][row] = moments.grad_norm_sq
                noise = moments.variance / int(batch.counts[row])
                self.points.setdefault(row, []).append(
                    (theta[row].detach().cpu().clone(), gradient[row].detach().cpu().clone(), noise)
                )

    def report(self, rows: Any) -> None:
        for row, points in self.points.items():
            if len(points) >= 2:
                (t0, g0, n0), (t1, g1, n1) = points[:2]
                found = secant_smoothness(t0, t1, g0, g1, n0, n1)
                if found is not None:
                    self.values["bound_smoothness"][row] = found
        for name, values in self.values.items():
            if not bool(values.isnan().all()):
                rows.report(name, values)


def row_bound_statistics(rows: int) -> RowBounds:
    return RowBounds(rows)
