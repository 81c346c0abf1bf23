"""Theorem 1's constants from an agent's own trajectories (common/learning/bounds.py), checked
against their exact values on the tabular MDP of tests/tabular_mdp.py, where every trajectory and
its probability can be enumerated: σ² = Σ_τ p(τ) ‖g(τ) − ∇J‖², M = Σ_τ p(τ) ‖g(τ)‖², ‖∇J‖² from
the exact objective. The Monte-Carlo means of the per-batch estimates must land within 4
standard errors (from the estimates' own spread) of the exact values, and a variance formula
with the classic bias (dividing by B instead of B − 1) must not."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import torch
from tabular_mdp import (
    enumerate_trajectories,
    exact_gradient,
    exact_objective,
    sample_batches,
    seeded_policy,
)

from fedhpg.common.learning.bounds import (
    gradient_moments,
    moments_from_sums,
    secant_smoothness,
    theorem1_terms,
)
from fedhpg.common.learning.estimators import estimator_coefficients, per_trajectory_gradients
from fedhpg.common.learning.policies import TabularSoftmaxPolicy

GAMMA = 0.9
BATCH = 8
NUM_BATCHES = 1500
Z_LIMIT = 4.0


def _per_trajectory(
    policy: TabularSoftmaxPolicy, estimator: str, obs, actions, rewards, alive
) -> torch.Tensor:
    coefficients = estimator_coefficients(
        estimator, torch.as_tensor(rewards), torch.as_tensor(alive), gamma=GAMMA, baseline="none"
    )
    return per_trajectory_gradients(
        policy, torch.as_tensor(obs), torch.as_tensor(actions), coefficients
    ).to(torch.float64)


@functools.cache
def _exact(estimator: str) -> tuple[float, float, float]:
    """(σ², M, ‖∇J‖²) at the seeded policy, by enumeration, in float64."""
    policy = seeded_policy(3).double()
    paths = enumerate_trajectories(policy.logits)
    grads = _per_trajectory(policy, estimator, paths.obs, paths.actions, paths.rewards, paths.alive)
    p = torch.from_numpy(paths.probability)
    true = exact_gradient(policy.logits.detach(), GAMMA).reshape(-1).to(torch.float64)
    assert torch.allclose(p @ grads, true, atol=1e-10)  # the enumeration's mean is ∇J
    variance = float(p @ (grads - true).square().sum(dim=1))
    return variance, float(p @ grads.square().sum(dim=1)), float(true.square().sum())


@functools.cache
def _sampled(estimator: str) -> list[torch.Tensor]:
    policy = seeded_policy(3)
    batches = sample_batches(policy, batch_size=BATCH, num_batches=NUM_BATCHES, seed=11)
    return [
        _per_trajectory(policy, estimator, b.obs, b.actions, b.rewards, b.alive) for b in batches
    ]


def _z(values: np.ndarray, exact: float) -> float:
    return abs(values.mean() - exact) / (values.std(ddof=1) / np.sqrt(values.size))


@pytest.mark.parametrize("estimator", ["gpomdp", "reinforce"])
def test_batch_estimates_converge_to_the_exact_constants(estimator: str) -> None:
    variance, second_moment, grad_norm_sq = _exact(estimator)
    moments = [gradient_moments(rows) for rows in _sampled(estimator)]
    sigma2 = np.array([m.variance for m in moments])
    assert _z(sigma2, variance) < Z_LIMIT
    assert _z(np.array([m.second_moment for m in moments]), second_moment) < Z_LIMIT
    assert _z(np.array([m.grad_norm_sq for m in moments]), grad_norm_sq) < Z_LIMIT
    # The test can tell: the 1/B variance (biased by (B − 1)/B) is far outside the tolerance.
    assert _z(sigma2 * (BATCH - 1) / BATCH, variance) > Z_LIMIT
    # and the naive ‖ḡ‖² (biased by σ²/B) for the gradient norm
    naive = np.array([float(rows.mean(dim=0).square().sum()) for rows in _sampled(estimator)])
    assert _z(naive, grad_norm_sq) > Z_LIMIT


def test_moments_from_sums_equal_those_of_the_matrix() -> None:
    rows = torch.randn(13, 7, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    direct = gradient_moments(rows)
    from_sums = moments_from_sums(rows.sum(dim=0), float(rows.square().sum()), 13)
    assert direct == pytest.approx(from_sums)
    centred = rows - rows.mean(dim=0)
    assert direct.variance == pytest.approx(float(centred.square().sum()) / 12, rel=1e-12)
    with pytest.raises(ValueError, match="at least 2"):
        moments_from_sums(rows[0], 1.0, 1)


def test_secant_smoothness_from_exact_and_from_noisy_gradients() -> None:
    """Exact gradients: the secant is ‖H δ‖/‖δ‖ for the mean Hessian on the segment, so at most
    its largest |eigenvalue|. Noisy batch gradients: subtracting the two estimates' variances
    makes the squared difference unbiased (mean within 4 standard errors of the exact one)."""
    policy = seeded_policy(3)
    before = policy.logits.detach().to(torch.float64)
    direction = torch.randn(before.shape, generator=torch.Generator().manual_seed(5))
    after = before + 0.01 * direction.to(torch.float64)
    g0, g1 = (exact_gradient(x, GAMMA).reshape(-1) for x in (before, after))
    secant = secant_smoothness(before, after, g0, g1, 0.0, 0.0)
    hessian = torch.autograd.functional.hessian(
        lambda x: exact_objective(x.reshape(before.shape), GAMMA), (before + after).reshape(-1) / 2
    )
    largest = float(torch.linalg.eigvalsh(hessian).abs().max())
    assert secant is not None and 0 < secant <= largest * 1.01
    assert secant_smoothness(before, before, g0, g1, 0.0, 0.0) is None

    moved = TabularSoftmaxPolicy(num_states=before.shape[0], num_actions=before.shape[1])
    with torch.no_grad():
        moved.logits.copy_(after.to(torch.float32))
    far = sample_batches(moved, batch_size=BATCH, num_batches=NUM_BATCHES, seed=12)
    far_rows = [_per_trajectory(moved, "gpomdp", b.obs, b.actions, b.rewards, b.alive) for b in far]
    exact_sq = float((g1 - g0).square().sum())
    debiased = []
    for near, rows in zip(_sampled("gpomdp"), far_rows, strict=True):
        m0, m1 = gradient_moments(near), gradient_moments(rows)
        difference = float((rows.mean(dim=0) - near.mean(dim=0)).square().sum())
        debiased.append(difference - m0.variance / BATCH - m1.variance / BATCH)
    assert _z(np.array(debiased), exact_sq) < Z_LIMIT


def test_theorem1_terms() -> None:
    common = dict(gap=10.0, step_size=0.01, smoothness=5.0, second_moment=4.0, rounds=100)
    one_step = theorem1_terms(
        **common, variances=[2.0, 3.0], local_iters=[1, 1], batch_sizes=[4, 8]
    )
    # τ_k = 1: no local drift and no heterogeneity term (α_A = α_B = 0), only the first two
    assert one_step.local_drift == 0.0 and one_step.heterogeneity == 0.0
    assert one_step.optimisation == pytest.approx(2 * 10.0 / (0.01 * 1 * 100))
    assert one_step.variance == pytest.approx(0.05 / 2 * (2.0 / 4 + 3.0 / 8))
    assert one_step.step_size_ok  # 0.01 < 1/L = 0.2
    many = theorem1_terms(**common, variances=[2.0, 3.0], local_iters=[2, 3], batch_sizes=[4, 8])
    # τ = (2, 3): τ̄ = 2.5, α_A = (6 + 30)/12 = 3, α_B = (2 + 6)/2 = 4
    assert many.local_drift == pytest.approx(0.05**2 / (6 * 2 * 2.5) * (2.0 * 6 / 4 + 3.0 * 30 / 8))
    assert many.heterogeneity == pytest.approx(0.05 * 4.0 / 2.5 * (0.05 * 3 + (1 - 0.025) * 4))
    bigger = theorem1_terms(
        **common, variances=[2.0, 3.0], local_iters=[2, 3], batch_sizes=[40, 80]
    )
    assert bigger.variance == pytest.approx(many.variance / 10)
    assert bigger.local_drift == pytest.approx(many.local_drift / 10)
    assert not theorem1_terms(
        **{**common, "step_size": 0.3}, variances=[1.0], local_iters=[1], batch_sizes=[1]
    ).step_size_ok


def test_a_run_reports_the_estimates_per_agent_and_theta_is_unchanged(tmp_path: Path) -> None:
    """algo.bound_estimates through a whole run: in process (GridWorld's tabular policy, the
    loop path) and over the wire (real agent processes): every agent's three figures in its
    round record, and θ̃ bit for bit that of the same run without them."""
    from fedhpg.server.commands import api

    keys = ["rounds=2", "eval.every=10", "agents=homogeneous4", "agents.budget.batch_size=[4]"]
    plain = api.run(overrides=keys)
    assert all("bound" not in record for record in plain.records)
    for distributed in (False, True):
        measured = api.run(
            overrides=[*keys, "algo.bound_estimates=true"],
            distributed=distributed,
            out_dir=tmp_path / f"distributed-{distributed}",
        )
        assert torch.equal(measured.theta, plain.theta)
        for record in measured.records:
            for agent in record["agents"]:
                assert agent["bound_variance"] >= 0 and agent["bound_second_moment"] > 0
                assert agent["bound_second_moment"] >= agent["bound_grad_norm_sq"]
                assert agent["bound_smoothness"] >= 0  # τ = 2 (the default): a secant for L
            # the round's eq. 7, from exactly these agents' figures (B = 4, τ = 2, T = 2)
            agents, bound = record["agents"], record["bound"]
            expected = theorem1_terms(
                gap=1.0,
                step_size=measured.config.algo.step_size,
                smoothness=max(a["bound_smoothness"] for a in agents),
                second_moment=max(a["bound_second_moment"] for a in agents),
                variances=[a["bound_variance"] for a in agents],
                local_iters=[2] * 4,
                batch_sizes=[4] * 4,
                rounds=2,
            )
            assert bound["agents"] == 4
            assert bound["optimisation_per_unit_gap"] == pytest.approx(expected.optimisation)
            assert bound["local_drift"] == pytest.approx(expected.local_drift)
            assert bound["variance"] == pytest.approx(expected.variance)
            assert bound["heterogeneity"] == pytest.approx(expected.heterogeneity)
            assert bound["step_size_ok"] == expected.step_size_ok
