"""REINFORCE (eq. 5) and GPOMDP (eq. 6) proved against the exact gradient of a tabular MDP.

Two kinds of evidence, both on the MDP of :mod:`tabular_mdp`:

- Exact, no sampling noise: the MDP has ~2·10⁴ possible trajectories, so E[g] of an
  estimator without baseline is a finite probability-weighted sum, computed with the library's
  own :func:`estimate_gradient` (it is linear in the coefficients). It must equal ∇J to
  float64 precision.
- Monte-Carlo, through the real sampler: G = 6250 independent batches of B = 8 trajectories,
  one :func:`estimate_gradient` call per batch (so the leave-one-out "mean" baseline works on
  B > 1 as in training). The mean of the G batch estimates must lie within 4 standard errors
  of ∇J on every coordinate. For the 8 informative coordinates and a normal mean, a false
  alarm has probability at most 8 · 6.3e-5 = 5e-4 per configuration; seeds are fixed anyway.
  The one tolerance beyond that is :data:`STDERR_FLOOR`.

The same check must *reject* deliberately broken estimators by more than 6 standard errors:
that is what shows it has the power to catch real mistakes.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import pytest
import torch
from oracle import TrajectoryBatch, sample_trajectories
from tabular_mdp import (
    HORIZON,
    NUM_ACTIONS,
    TERMINAL,
    CoefficientFn,
    Enumeration,
    TabularMDPBatchEnv,
    enumerate_trajectories,
    exact_gradient,
    exact_objective,
    sample_batches,
    seeded_policy,
)

from fedhpg.common.learning.estimators import (
    estimate_gradient,
    estimator_coefficients,
    per_trajectory_gradients,
)
from fedhpg.common.learning.policies import TabularSoftmaxPolicy

GAMMA = 0.9
GAMMAS = (0.9, 1.0)
BATCH_SIZE = 8
NUM_BATCHES = 6250  # 50 000 trajectories: broken estimators land ≳ 8 s.e. off
Z_LIMIT = 4.0  # an unbiased estimator must stay within this many standard errors
Z_BROKEN = 6.0  # a broken one must be at least this far off on some coordinate
# Only for coordinates with zero sample variance: the terminal state's logits are never scored
# at an alive step, so every batch estimate there is exactly 0, as is ∇J. The floor turns the
# 0/0 into z = 0 there; any non-zero deviation on such a coordinate still gives a huge z.
STDERR_FLOOR = 1e-9
ESTIMATORS = ("reinforce", "gpomdp")
BASELINES = ("none", "mean")


class Batch(NamedTuple):
    """One sampled batch as the tensors the estimators take."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    alive: torch.Tensor


def _as_batch(trajectories: TrajectoryBatch) -> Batch:
    return Batch(
        obs=torch.from_numpy(trajectories.obs),
        actions=torch.from_numpy(trajectories.actions),
        rewards=torch.from_numpy(trajectories.rewards),
        alive=torch.from_numpy(trajectories.alive),
    )


def max_standard_errors(estimates: torch.Tensor, exact: torch.Tensor) -> float:
    """max over coordinates of |mean(g_i) − ∇J| / (std(g_i) / √G) for G estimates [G, d].

    The standard error comes from the estimates themselves, so the tolerance scales with the
    estimator's own variance instead of being a hand-tuned constant.
    """
    estimates = estimates.to(torch.float64)
    mean = estimates.mean(dim=0)
    stderr = estimates.std(dim=0) / estimates.shape[0] ** 0.5
    return float(((mean - exact.to(torch.float64)).abs() / stderr.clamp_min(STDERR_FLOOR)).max())


def batch_estimates(
    policy: TabularSoftmaxPolicy,
    batches: list[Batch],
    coefficients: CoefficientFn,
    *,
    wrong_actions: bool = False,
) -> torch.Tensor:
    """[G, d]: :func:`estimate_gradient` of each batch, its coefficients (and so its baseline)
    computed within the batch. ``wrong_actions`` scores a = 1 − a instead (a broken estimator)."""
    rows = []
    for batch in batches:
        actions = NUM_ACTIONS - 1 - batch.actions if wrong_actions else batch.actions
        coef = coefficients(batch.rewards, batch.alive)
        rows.append(estimate_gradient(policy, batch.obs, actions, coef))
    return torch.stack(rows).to(torch.float64)


def library_coefficients(estimator: str, *, gamma: float, baseline: str) -> CoefficientFn:
    return functools.partial(
        estimator_coefficients,
        estimator,  # type: ignore[arg-type]
        gamma=gamma,
        baseline=baseline,  # type: ignore[arg-type]
    )


# -- deliberately broken coefficient functions (for the power checks) -------------------------
# Each is the library's default (GPOMDP with the leave-one-out per-step baseline) with exactly
# one mistake. The baseline does not change what each one converges to (it is independent of
# the trajectory it centres) but lowers its variance, so the mistake stands out more.


def _centred(values: torch.Tensor, baseline: str) -> torch.Tensor:
    """With ``baseline="mean"``: values[:, b] minus the mean of the other columns (written
    out here, not imported from the library)."""
    if baseline == "none":
        return values
    others = (values.sum(dim=1, keepdim=True) - values) / (values.shape[1] - 1)
    return values - others


def _discounted(rewards: torch.Tensor) -> torch.Tensor:
    return (GAMMA ** torch.arange(rewards.shape[0], dtype=rewards.dtype))[:, None] * rewards


def _reward_to_go(step_values: torch.Tensor) -> torch.Tensor:
    return step_values.flip(0).cumsum(0).flip(0)


def undiscounted_gpomdp(
    rewards: torch.Tensor, alive: torch.Tensor, baseline: str = "mean"
) -> torch.Tensor:
    """Broken: Σ_{h≥t} (r_h − C_h), the γ^h dropped although the objective has γ = 0.9."""
    return alive.to(rewards.dtype) * _reward_to_go(_centred(rewards, baseline))


def discounted_from_t_gpomdp(
    rewards: torch.Tensor, alive: torch.Tensor, baseline: str = "mean"
) -> torch.Tensor:
    """Broken (a common real-world slip): Σ_{h≥t} γ^{h−t} (r_h − C_h), discounting from the
    scored step instead of from 0; eq. (6) weighs r_h by γ^h."""
    centred = _centred(rewards, baseline)
    coef = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = centred[t] + GAMMA * running
        coef[t] = running
    return alive.to(rewards.dtype) * coef


def off_by_one_gpomdp(
    rewards: torch.Tensor, alive: torch.Tensor, baseline: str = "mean"
) -> torch.Tensor:
    """Broken: Σ_{h>t} (γ^h r_h − C_h), leaving out the reward of the scored step itself."""
    centred = _centred(_discounted(rewards), baseline)
    return alive.to(rewards.dtype) * (_reward_to_go(centred) - centred)


def inclusive_mean_reinforce(rewards: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
    """REINFORCE with C = the batch mean return *including* the trajectory itself. Its
    expectation is (B − 1)/B · ∇J: the reason the library leaves each trajectory out."""
    returns = (GAMMA ** torch.arange(rewards.shape[0], dtype=rewards.dtype)) @ rewards
    return alive.to(rewards.dtype) * (returns - returns.mean()).unsqueeze(0)


# -- fixtures ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def policy() -> TabularSoftmaxPolicy:
    return seeded_policy(seed=0)


@pytest.fixture(scope="module")
def sampled(policy: TabularSoftmaxPolicy) -> list[TrajectoryBatch]:
    return sample_batches(policy, batch_size=BATCH_SIZE, num_batches=NUM_BATCHES, seed=1)


@pytest.fixture(scope="module")
def batches(sampled: list[TrajectoryBatch]) -> list[Batch]:
    return [_as_batch(trajectories) for trajectories in sampled]


@pytest.fixture(scope="module")
def estimates(
    policy: TabularSoftmaxPolicy, batches: list[Batch]
) -> Callable[[str, str, float], torch.Tensor]:
    """Batch estimates of the library estimators, computed once per configuration and shared
    by the bias and variance tests (same samples for every configuration)."""

    @functools.cache
    def compute(estimator: str, baseline: str, gamma: float) -> torch.Tensor:
        coefficients = library_coefficients(estimator, gamma=gamma, baseline=baseline)
        return batch_estimates(policy, batches, coefficients)

    return compute


@pytest.fixture(scope="module")
def enumeration(policy: TabularSoftmaxPolicy) -> Enumeration:
    return enumerate_trajectories(policy.logits)


def _double(policy: TabularSoftmaxPolicy) -> TabularSoftmaxPolicy:
    """A float64 copy: the exact (noise-free) checks compare to 1e-10, below float32 round-off."""
    return copy.deepcopy(policy).double()


def _exact_expectation(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration, coefficients: CoefficientFn
) -> torch.Tensor:
    """E[g] = Σ_τ p(τ) g(τ) for a baseline-free estimator: since estimate_gradient computes
    (1/N) Σ_τ g(τ) and g is linear in the coefficients, scaling column τ by N · p(τ) gives
    the exact expectation in one call."""
    rewards = torch.from_numpy(enumeration.rewards)
    alive = torch.from_numpy(enumeration.alive)
    weights = torch.from_numpy(enumeration.probability) * enumeration.probability.size
    coef = coefficients(rewards, alive) * weights
    obs = torch.from_numpy(enumeration.obs)
    return estimate_gradient(_double(policy), obs, torch.from_numpy(enumeration.actions), coef)


# -- the test MDP, the exact objective and the sampler agree ----------------------------------


@pytest.mark.parametrize("gamma", GAMMAS)
def test_enumeration_matches_forward_recursion(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration, gamma: float
) -> None:
    returns = (gamma ** np.arange(HORIZON)) @ enumeration.rewards
    assert enumeration.probability.sum() == pytest.approx(1.0, abs=1e-12)
    assert float(enumeration.probability @ returns) == pytest.approx(
        float(exact_objective(policy.logits.detach(), gamma)), abs=1e-12
    )
    assert not enumeration.alive[-1].all(), "some trajectories end before the horizon"


def test_exact_gradient_matches_finite_differences(policy: TabularSoftmaxPolicy) -> None:
    """∇J from autograd against central differences of J (float64; step 1e-6)."""
    theta = policy.logits.detach().to(torch.float64)
    exact = exact_gradient(theta, GAMMA)
    numeric = torch.zeros_like(exact)
    for i in range(theta.numel()):
        step = torch.zeros(theta.numel(), dtype=torch.float64)
        step[i] = 1e-6
        delta = step.reshape(theta.shape)
        numeric[i] = (
            exact_objective(theta + delta, GAMMA) - exact_objective(theta - delta, GAMMA)
        ) / 2e-6
    torch.testing.assert_close(exact, numeric, atol=1e-8, rtol=1e-6)
    assert (exact.reshape(theta.shape)[TERMINAL] == 0).all()


@pytest.mark.parametrize("gamma", GAMMAS)
def test_sampler_return_matches_exact_objective(
    policy: TabularSoftmaxPolicy, sampled: list[TrajectoryBatch], gamma: float
) -> None:
    """Validates the BatchEnv and the real sampler against J(θ), independently of any
    gradient estimator."""
    returns = np.concatenate([trajectories.returns(gamma) for trajectories in sampled])
    exact = float(exact_objective(policy.logits.detach(), gamma))
    stderr = returns.std(ddof=1) / returns.size**0.5
    z = abs(returns.mean() - exact) / stderr
    assert z < Z_LIMIT, f"mean return {returns.mean():.4f} vs J = {exact:.4f}: {z:.2f} s.e."


def test_samples_exercise_early_termination(sampled: list[TrajectoryBatch]) -> None:
    lengths = np.concatenate([trajectories.lengths for trajectories in sampled])
    assert (lengths < HORIZON).mean() > 0.3, "many trajectories end early (alive masks)"
    assert any(trajectories.obs.shape[0] < HORIZON for trajectories in sampled), (
        "some whole batches end early (the sampler's early exit, T < H)"
    )


def test_env_is_reproducible_from_its_seed(policy: TabularSoftmaxPolicy) -> None:
    first, second = (
        sample_trajectories(
            TabularMDPBatchEnv(16), policy, np.random.default_rng(7), horizon=HORIZON
        )
        for _ in range(2)
    )
    np.testing.assert_array_equal(first.obs, second.obs)
    np.testing.assert_array_equal(first.rewards, second.rewards)


# -- exact expectations (no sampling noise) ---------------------------------------------------


@pytest.mark.parametrize("gamma", GAMMAS)
@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_exact_expectation_equals_gradient(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration, estimator: str, gamma: float
) -> None:
    coefficients = library_coefficients(estimator, gamma=gamma, baseline="none")
    expectation = _exact_expectation(policy, enumeration, coefficients)
    torch.testing.assert_close(
        expectation, exact_gradient(policy.logits, gamma), atol=1e-10, rtol=0
    )


def test_exact_expectation_rejects_broken_estimators(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration
) -> None:
    exact = exact_gradient(policy.logits, GAMMA)
    for broken in (undiscounted_gpomdp, discounted_from_t_gpomdp, off_by_one_gpomdp):
        no_baseline = functools.partial(broken, baseline="none")
        error = (_exact_expectation(policy, enumeration, no_baseline) - exact).abs().max()
        assert error > 1e-2, f"{broken.__name__} is not biased on this MDP ({error:.2e})"


def test_exact_gpomdp_variance_below_reinforce(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration
) -> None:
    """tr Cov g = E‖g‖² − ‖E g‖², exactly, for single-trajectory estimates without baseline."""
    obs = torch.from_numpy(enumeration.obs)
    actions = torch.from_numpy(enumeration.actions)
    rewards = torch.from_numpy(enumeration.rewards)
    alive = torch.from_numpy(enumeration.alive)
    probability = torch.from_numpy(enumeration.probability)
    exact = exact_gradient(policy.logits, GAMMA)
    variance = {}
    for estimator in ESTIMATORS:
        coef = library_coefficients(estimator, gamma=GAMMA, baseline="none")(rewards, alive)
        rows = per_trajectory_gradients(_double(policy), obs, actions, coef)
        variance[estimator] = float(probability @ rows.pow(2).sum(dim=1) - exact.pow(2).sum())
    assert 0 < variance["gpomdp"] < variance["reinforce"], variance


# -- identities of the batch estimator --------------------------------------------------------


def test_batch_gradient_is_mean_of_per_trajectory_gradients(
    policy: TabularSoftmaxPolicy, sampled: list[TrajectoryBatch]
) -> None:
    batch = _as_batch(sampled[0])
    for estimator in ESTIMATORS:
        coef = library_coefficients(estimator, gamma=GAMMA, baseline="mean")(
            batch.rewards, batch.alive
        )
        for net, tol in ((policy, 1e-6), (_double(policy), 1e-12)):
            rows = per_trajectory_gradients(net, batch.obs, batch.actions, coef)
            whole = estimate_gradient(net, batch.obs, batch.actions, coef)
            assert rows.shape == (BATCH_SIZE, whole.numel())
            torch.testing.assert_close(rows.mean(dim=0), whole, atol=tol, rtol=tol)


def test_batch_gradient_is_linear_in_coefficients(
    policy: TabularSoftmaxPolicy, sampled: list[TrajectoryBatch]
) -> None:
    batch = _as_batch(sampled[1])
    net = _double(policy)
    first = estimator_coefficients("reinforce", batch.rewards, batch.alive, gamma=GAMMA)
    second = estimator_coefficients("gpomdp", batch.rewards, batch.alive, gamma=GAMMA)

    def grad(coef: torch.Tensor) -> torch.Tensor:
        return estimate_gradient(net, batch.obs, batch.actions, coef)

    torch.testing.assert_close(
        grad(2.5 * first - 0.75 * second),
        2.5 * grad(first) - 0.75 * grad(second),
        atol=1e-12,
        rtol=1e-12,
    )
    assert torch.equal(
        grad(torch.zeros_like(first)), torch.zeros(net.num_params, dtype=torch.float64)
    )


# -- Monte-Carlo: unbiased through the real sampler -------------------------------------------


@pytest.mark.parametrize("gamma", GAMMAS)
@pytest.mark.parametrize("baseline", BASELINES)
@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_estimator_is_unbiased(
    policy: TabularSoftmaxPolicy,
    estimates: Callable[[str, str, float], torch.Tensor],
    estimator: str,
    baseline: str,
    gamma: float,
) -> None:
    z = max_standard_errors(
        estimates(estimator, baseline, gamma), exact_gradient(policy.logits, gamma)
    )
    assert z < Z_LIMIT, f"{estimator}/{baseline}/γ={gamma}: {z:.2f} standard errors from ∇J"


@pytest.mark.parametrize("baseline", BASELINES)
def test_gpomdp_variance_does_not_exceed_reinforce(
    estimates: Callable[[str, str, float], torch.Tensor], baseline: str
) -> None:
    """Same samples, same baseline: total variance (trace of the covariance) of the batch
    estimates. Observed GPOMDP/REINFORCE ratio: 0.40 without baseline, 0.57 with "mean"."""
    gpomdp = float(estimates("gpomdp", baseline, GAMMA).var(dim=0).sum())
    reinforce = float(estimates("reinforce", baseline, GAMMA).var(dim=0).sum())
    assert gpomdp <= reinforce, f"{baseline}: gpomdp {gpomdp:.4f} > reinforce {reinforce:.4f}"


def test_mean_baseline_reduces_variance(
    estimates: Callable[[str, str, float], torch.Tensor],
) -> None:
    for estimator in ESTIMATORS:
        with_baseline = float(estimates(estimator, "mean", GAMMA).var(dim=0).sum())
        without = float(estimates(estimator, "none", GAMMA).var(dim=0).sum())
        assert with_baseline < without, (estimator, with_baseline, without)


# -- power: the same Monte-Carlo check rejects broken estimators ------------------------------


@pytest.mark.parametrize(
    "broken", [undiscounted_gpomdp, discounted_from_t_gpomdp, off_by_one_gpomdp]
)
def test_broken_coefficients_are_caught(
    policy: TabularSoftmaxPolicy, batches: list[Batch], broken: CoefficientFn
) -> None:
    z = max_standard_errors(
        batch_estimates(policy, batches, broken), exact_gradient(policy.logits, GAMMA)
    )
    assert z > Z_BROKEN, f"{broken.__name__} only {z:.2f} standard errors off"


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_log_prob_of_the_wrong_action_is_caught(
    policy: TabularSoftmaxPolicy, batches: list[Batch], estimator: str
) -> None:
    coefficients = library_coefficients(estimator, gamma=GAMMA, baseline="mean")
    estimates = batch_estimates(policy, batches, coefficients, wrong_actions=True)
    z = max_standard_errors(estimates, exact_gradient(policy.logits, GAMMA))
    assert z > Z_BROKEN, f"{estimator} with a = 1 − a only {z:.2f} standard errors off"


def test_inclusive_batch_mean_baseline_is_biased_by_b_minus_1_over_b(
    policy: TabularSoftmaxPolicy, batches: list[Batch]
) -> None:
    """A batch-mean baseline that includes τ_b shrinks E[g] to (B − 1)/B · ∇J: the check
    rejects it against ∇J and accepts it against the shrunk gradient."""
    estimates = batch_estimates(policy, batches, inclusive_mean_reinforce)
    exact = exact_gradient(policy.logits, GAMMA)
    # The bias is only ∇J / 8 here (≈ 8 s.e. expected), so the claim checked is the one that
    # matters: the unbiasedness check fails, and passes against the shrunk gradient.
    z_unbiased = max_standard_errors(estimates, exact)
    assert z_unbiased > Z_LIMIT, f"inclusive baseline only {z_unbiased:.2f} s.e. from ∇J"
    z_shrunk = max_standard_errors(estimates, (BATCH_SIZE - 1) / BATCH_SIZE * exact)
    assert z_shrunk < Z_LIMIT, f"{z_shrunk:.2f} s.e. from (B − 1)/B · ∇J"
