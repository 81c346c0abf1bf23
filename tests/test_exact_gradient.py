"""REINFORCE and GPOMDP against the exact gradient of a tiny tabular MDP.

Every check is statistical with a tolerance derived from the sample variance: the mean of G
independent batch estimates must lie within 4 standard errors of ∇J on every coordinate (for
16 coordinates the chance of a false alarm is ~1e-3). A deliberately broken estimator must fail
the very same check, which shows the test has the power to catch real mistakes.
"""

from __future__ import annotations

import pytest
import torch
from exact_mdp import (
    BATCH,
    GROUPS,
    HORIZON,
    Z_LIMIT,
    batch_estimates,
    exact_gradient,
    exact_objective,
    make_policy,
    max_standard_errors,
    sample,
)

from fedhpg.common.estimators import (
    estimate_gradient,
    estimator_coefficients,
    gpomdp_coefficients,
    per_trajectory_gradients,
    reinforce_coefficients,
)
from fedhpg.common.policies import TabularSoftmaxPolicy
from fedhpg.common.rollout import TrajectoryBatch

GAMMA = 0.9


@pytest.fixture(scope="module")
def setting() -> tuple[TabularSoftmaxPolicy, TrajectoryBatch, torch.Tensor]:
    policy = make_policy()
    trajectories = sample(policy, GROUPS * BATCH, seed=1)
    return policy, trajectories, exact_gradient(policy.logits, GAMMA)


def test_sampler_matches_the_exact_objective(setting) -> None:
    policy, trajectories, _ = setting
    returns = trajectories.returns(GAMMA)
    exact = float(exact_objective(policy.logits.detach(), GAMMA))
    stderr = returns.std() / len(returns) ** 0.5
    assert abs(returns.mean() - exact) < Z_LIMIT * stderr
    assert (trajectories.lengths < HORIZON).any(), "some trajectories end early"


@pytest.mark.parametrize("estimator", ["reinforce", "gpomdp"])
@pytest.mark.parametrize("baseline", ["none", "mean"])
def test_estimator_is_unbiased(setting, estimator: str, baseline: str) -> None:
    policy, trajectories, exact = setting

    def coefficients(rewards: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        return estimator_coefficients(estimator, rewards, alive, gamma=GAMMA, baseline=baseline)  # type: ignore[arg-type]

    z = max_standard_errors(batch_estimates(policy, trajectories, coefficients), exact)
    assert z < Z_LIMIT, f"{estimator}/{baseline}: {z:.2f} standard errors from ∇J"


def test_undiscounted_case_is_unbiased_too() -> None:
    policy = make_policy(seed=2)
    trajectories = sample(policy, GROUPS * BATCH, seed=3)
    exact = exact_gradient(policy.logits, 1.0)
    for name in ("reinforce", "gpomdp"):
        estimates = batch_estimates(
            policy, trajectories, lambda r, a, n=name: estimator_coefficients(n, r, a, gamma=1.0)
        )
        assert max_standard_errors(estimates, exact) < Z_LIMIT, name


@pytest.mark.parametrize("baseline", ["none", "mean"])
def test_gpomdp_variance_does_not_exceed_reinforce(setting, baseline: str) -> None:
    policy, trajectories, _ = setting
    total_variance = {}
    for name in ("reinforce", "gpomdp"):
        estimates = batch_estimates(
            policy,
            trajectories,
            lambda r, a, n=name: estimator_coefficients(n, r, a, gamma=GAMMA, baseline=baseline),
        )
        total_variance[name] = float(estimates.var(dim=0).sum())
    assert total_variance["gpomdp"] <= total_variance["reinforce"], total_variance


def test_batch_gradient_is_the_mean_of_per_trajectory_gradients(setting) -> None:
    policy, trajectories, _ = setting
    head = slice(0, 16)
    rewards = torch.from_numpy(trajectories.rewards[:, head])
    alive = torch.from_numpy(trajectories.alive[:, head])
    obs = torch.from_numpy(trajectories.obs[:, head])
    actions = torch.from_numpy(trajectories.actions[:, head])
    coef = gpomdp_coefficients(rewards, alive, gamma=GAMMA)
    batch = estimate_gradient(policy, obs, actions, coef)
    rows = per_trajectory_gradients(policy, obs, actions, coef)
    torch.testing.assert_close(rows.mean(dim=0), batch, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(estimate_gradient(policy, obs, actions, 3 * coef), 3 * batch)


# -- power: the same check rejects broken estimators ------------------------------------------


def test_dropping_the_discount_is_caught(setting) -> None:
    policy, trajectories, exact = setting

    def undiscounted(rewards: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        return gpomdp_coefficients(rewards, alive, gamma=1.0)  # γ^h dropped although γ = 0.9

    z = max_standard_errors(batch_estimates(policy, trajectories, undiscounted), exact)
    assert z > 6.0, f"broken estimator only {z:.2f} standard errors off"


def test_log_prob_of_the_wrong_action_is_caught(setting) -> None:
    policy, trajectories, exact = setting

    def correct(rewards: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        return reinforce_coefficients(rewards, alive, gamma=GAMMA)

    wrong = 1 - trajectories.actions
    z = max_standard_errors(batch_estimates(policy, trajectories, correct, actions=wrong), exact)
    assert z > 6.0, f"broken estimator only {z:.2f} standard errors off"


def test_a_batch_mean_baseline_that_includes_the_trajectory_is_biased(setting) -> None:
    """Why the 'mean' baseline leaves each trajectory out: including it scales the estimate by
    (B − 1)/B, which the test detects."""
    policy, trajectories, exact = setting

    def inclusive_mean(rewards: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        returns = (GAMMA ** torch.arange(rewards.shape[0], dtype=rewards.dtype)) @ rewards
        return alive.double() * (returns - returns.mean()).unsqueeze(0)

    z = max_standard_errors(batch_estimates(policy, trajectories, inclusive_mean), exact)
    assert z > Z_LIMIT, f"inclusive baseline only {z:.2f} standard errors off"
