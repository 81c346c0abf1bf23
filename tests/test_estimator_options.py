"""The estimator options used in practice (``algo.reward_to_go``, ``algo.normalize``): each
departure from eq. 5/6 is shown to be *biased* for ∇J on the tabular MDP, by how much (the
figures of docs/configuration.md, Estimator options), and the batched engine computes them as
the loop does.

Exact where the option keeps each trajectory's estimate a function of that trajectory alone
(reward-to-go from the step; per-episode standardisation without baseline): E[g] is then the
probability-weighted sum over every trajectory. Batch standardisation couples the trajectories
of a batch, so its E[g] is a Monte-Carlo mean over G batches with its standard error.

``python -m pytest tests/test_estimator_options.py -k figures -s`` prints the guide's table.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pytest
import torch
from oracle import sample_trajectories
from tabular_mdp import (
    HORIZON,
    CoefficientFn,
    Enumeration,
    TabularMDPBatchEnv,
    enumerate_trajectories,
    exact_gradient,
    seeded_policy,
)
from test_estimators_exact import (
    Z_BROKEN,
    Z_LIMIT,
    Batch,
    _as_batch,
    _exact_expectation,
    batch_estimates,
    max_standard_errors,
)

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.estimators import (
    estimate_gradient,
    estimator_coefficients,
    normalize_coefficients,
    per_trajectory_gradients,
)
from fedhpg.common.learning.policies import TabularSoftmaxPolicy, set_flat_params
from fedhpg.common.learning.worker import build_policy, initial_theta
from fedhpg.server.commands.api import resolve_config

GAMMA = 0.9
BATCH_SIZE = 8
NUM_BATCHES = 6250  # 50 000 trajectories, as tests/test_estimators_exact.py


def _coefficients(**options: str) -> functools.partial[torch.Tensor]:
    estimator = options.pop("estimator", "gpomdp")
    return functools.partial(estimator_coefficients, estimator, gamma=GAMMA, **options)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def policy() -> TabularSoftmaxPolicy:
    return seeded_policy(seed=0)


@pytest.fixture(scope="module")
def enumeration(policy: TabularSoftmaxPolicy) -> Enumeration:
    return enumerate_trajectories(policy.logits)


@pytest.fixture(scope="module")
def batches(policy: TabularSoftmaxPolicy) -> list[Batch]:
    """G independent batches of B from one sampler call over G·B environments (each batch is
    B of its columns; all share the longest trajectory's length, the alive masks say the rest)."""
    env = TabularMDPBatchEnv(BATCH_SIZE * NUM_BATCHES)
    whole = _as_batch(sample_trajectories(env, policy, np.random.default_rng(2), horizon=HORIZON))
    return [
        Batch(*(tensor[:, g * BATCH_SIZE : (g + 1) * BATCH_SIZE] for tensor in whole))
        for g in range(NUM_BATCHES)
    ]


def _batch_estimates(
    policy: TabularSoftmaxPolicy, batches: list[Batch], coefficients: CoefficientFn
) -> torch.Tensor:
    """[G, d]: each batch's estimate, its coefficients computed within the batch, as
    :func:`batch_estimates` gives them but with one per-trajectory gradient pass over all."""
    coef = torch.cat([coefficients(b.rewards, b.alive) for b in batches], dim=1)
    obs = torch.cat([b.obs for b in batches], dim=1)
    actions = torch.cat([b.actions for b in batches], dim=1)
    rows = per_trajectory_gradients(policy, obs, actions, coef)
    return rows.reshape(len(batches), BATCH_SIZE, -1).mean(dim=1).to(torch.float64)


@pytest.fixture(scope="module")
def estimates(policy: TabularSoftmaxPolicy, batches: list[Batch]) -> Callable[..., torch.Tensor]:
    """Batch estimates with the mean baseline per option set, computed once for the module."""

    @functools.cache
    def compute(**options: str) -> torch.Tensor:
        return _batch_estimates(policy, batches, _coefficients(baseline="mean", **options))

    return compute


@pytest.fixture(scope="module")
def exact(policy: TabularSoftmaxPolicy) -> torch.Tensor:
    return exact_gradient(policy.logits, GAMMA)


def _bias_figures(mean: torch.Tensor, exact: torch.Tensor) -> tuple[float, float]:
    """(‖E g − ∇J‖ / ‖∇J‖, cos(E g, ∇J)): the second is what survives a rescaling, which
    every standardising option applies."""
    mean, exact = mean.to(torch.float64), exact.to(torch.float64)
    relative = float((mean - exact).norm() / exact.norm())
    cosine = float(mean @ exact / (mean.norm() * exact.norm()))
    return relative, cosine


def test_the_one_pass_estimates_are_the_libraries_batch_estimates(
    policy: TabularSoftmaxPolicy, batches: list[Batch]
) -> None:
    coefficients = _coefficients(baseline="mean", normalize="batch")
    torch.testing.assert_close(
        _batch_estimates(policy, batches[:20], coefficients),
        batch_estimates(policy, batches[:20], coefficients),
        atol=1e-6,
        rtol=1e-5,
    )


# -- the defaults stay eq. 5/6: the options' "off" values change nothing ----------------------


def test_default_options_are_the_papers_coefficients(batches: list[Batch]) -> None:
    batch = batches[0]
    for estimator in ("reinforce", "gpomdp"):
        for baseline in ("none", "mean"):
            plain = estimator_coefficients(
                estimator,  # type: ignore[arg-type]
                batch.rewards,
                batch.alive,
                gamma=GAMMA,
                baseline=baseline,  # type: ignore[arg-type]
            )
            explicit = _coefficients(
                estimator=estimator, baseline=baseline, reward_to_go="from_start", normalize="none"
            )(batch.rewards, batch.alive)
            assert torch.equal(plain, explicit)


def test_reward_to_go_from_step_is_eq6_divided_by_gamma_t(batches: list[Batch]) -> None:
    """The departure is exactly the dropped γ^t; with γ = 1 there is none."""
    batch = batches[3]
    steps = batch.rewards.shape[0]
    for baseline in ("none", "mean"):
        eq6 = _coefficients(baseline=baseline)(batch.rewards, batch.alive)
        from_step = _coefficients(baseline=baseline, reward_to_go="from_step")(
            batch.rewards, batch.alive
        )
        scale = GAMMA ** torch.arange(steps, dtype=torch.float64)[:, None]
        torch.testing.assert_close(from_step * scale, eq6, atol=1e-12, rtol=1e-12)
        undiscounted = functools.partial(estimator_coefficients, "gpomdp", gamma=1.0)
        assert torch.allclose(
            undiscounted(batch.rewards, batch.alive, baseline=baseline),  # type: ignore[arg-type]
            undiscounted(batch.rewards, batch.alive, baseline=baseline, reward_to_go="from_step"),  # type: ignore[arg-type]
        )


def test_standardised_coefficients_have_zero_mean_and_unit_spread(batches: list[Batch]) -> None:
    batch = max(batches[:50], key=lambda b: int(b.alive.sum()))
    raw = _coefficients(baseline="mean")(batch.rewards, batch.alive)
    alive = batch.alive.bool()
    whole = normalize_coefficients(raw, batch.alive, "batch")[alive]
    assert float(whole.mean()) == pytest.approx(0.0, abs=1e-12)
    assert float(whole.pow(2).mean()) == pytest.approx(1.0, abs=1e-6)
    per_episode = normalize_coefficients(raw, batch.alive, "episode")
    for b in range(raw.shape[1]):
        column = per_episode[:, b][alive[:, b]]
        assert float(column.mean()) == pytest.approx(0.0, abs=1e-12)
    assert (per_episode[~alive] == 0).all() and (
        normalize_coefficients(raw, batch.alive, "batch")[~alive] == 0
    ).all()


# -- every departure is biased for ∇J, by the guide's figures ---------------------------------


def test_reward_to_go_from_step_is_biased_exactly(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration, exact: torch.Tensor
) -> None:
    expectation = _exact_expectation(
        policy, enumeration, _coefficients(baseline="none", reward_to_go="from_step")
    )
    relative, cosine = _bias_figures(expectation, exact)
    # Mostly a longer ∇J on this 4-step MDP (cos ≈ 0.9994): late steps weigh γ^t too much.
    print(f"\nexact, from_step, no baseline: {relative:.4f} of ‖∇J‖, cos {cosine:.4f}")
    assert relative > 0.05, f"from_step only {relative:.3f} of ‖∇J‖ off"


def test_from_step_with_the_mean_baseline_converges_to_its_own_biased_target(
    policy: TabularSoftmaxPolicy,
    enumeration: Enumeration,
    estimates: Callable[..., torch.Tensor],
    exact: torch.Tensor,
) -> None:
    """The leave-one-out baseline keeps E[g] where the option puts it (the exact E[g] without
    baseline), so the measured bias is the reward-to-go's alone; and the same Monte-Carlo
    check rejects it against ∇J."""
    target = _exact_expectation(
        policy, enumeration, _coefficients(baseline="none", reward_to_go="from_step")
    )
    sampled = estimates(reward_to_go="from_step")
    assert max_standard_errors(sampled, target) < Z_LIMIT
    assert max_standard_errors(sampled, exact) > Z_BROKEN


def test_episode_standardisation_is_biased_exactly(
    policy: TabularSoftmaxPolicy, enumeration: Enumeration, exact: torch.Tensor
) -> None:
    expectation = _exact_expectation(
        policy, enumeration, _coefficients(baseline="none", normalize="episode")
    )
    relative, cosine = _bias_figures(expectation, exact)
    print(f"\nexact, normalize=episode, no baseline: {relative:.4f} of ‖∇J‖, cos {cosine:.4f}")
    assert relative > 0.05, (relative, cosine)


BIASED: dict[str, dict[str, str]] = {
    "gpomdp, reward_to_go=from_step": dict(reward_to_go="from_step"),
    "gpomdp, normalize=episode": dict(normalize="episode"),
    "gpomdp, normalize=batch": dict(normalize="batch"),
    "reinforce, normalize=batch": dict(estimator="reinforce", normalize="batch"),
}


def test_bias_figures(estimates: Callable[..., torch.Tensor], exact: torch.Tensor) -> None:
    """Monte-Carlo figures of every biased option with the mean baseline (B = 8, as trained),
    printed for docs/configuration.md, Estimator options; each is far from ∇J (per coordinate,
    in standard errors of the mean; the ± is the norm of those standard errors over ‖∇J‖). Batch
    standardisation comes out mostly a shorter ∇J here (cos ≈ 0.999): its direction bias is
    too small to resolve with 5·10⁴ trajectories, so only the length is claimed."""
    print(f"\n| option (mean baseline, B={BATCH_SIZE}) | ‖E g − ∇J‖/‖∇J‖ | cos(E g, ∇J) |")
    for label, options in BIASED.items():
        sampled = estimates(**options)
        relative, cosine = _bias_figures(sampled.mean(dim=0), exact)
        stderr = float(sampled.std(dim=0).norm() / sampled.shape[0] ** 0.5 / exact.norm())
        print(f"| {label} | {relative:.3f} ± {stderr:.3f} | {cosine:.4f} |")
        assert max_standard_errors(sampled, exact) > Z_BROKEN, label


# -- the batched engine computes the options as the loop does ----------------------------------


@pytest.mark.parametrize(
    "options",
    [
        ("algo.reward_to_go=from_step",),
        ("algo.normalize=batch",),
        ("algo.normalize=episode",),
        ("algo.reward_to_go=from_step", "algo.normalize=batch", "algo.baseline=none"),
        ("algo.estimator=reinforce", "algo.normalize=batch"),
    ],
    ids=["from_step", "batch", "episode", "from_step-batch-nobaseline", "reinforce-batch"],
)
def test_the_engines_gradient_is_the_oracles_with_the_options(options: tuple[str, ...]) -> None:
    """Three CartPole agents with other batch sizes side by side: each row's gradient with the
    option is the per-agent autograd oracle's on that row's own trajectories."""
    run = resolve_config(overrides=[
        "env=cartpole", "algo.engine=torch", "policy.hidden=[8]", "agents.num_agents=3",
        "agents.budget.batch_size=[4,6,5]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
        "env.horizon=80", *options,
    ])  # fmt: skip
    engine = Engine(run, variants_of(run, [0, 1, 2]))
    rows = engine.begin(2, initial_theta(engine.variants[0], run), [0, 1, 2])
    generator = torch.Generator().manual_seed(4)
    theta = rows.theta + 0.3 * torch.randn(rows.theta.shape, generator=generator)
    batch = rows.sample(theta, torch.tensor([4, 6, 5]), iteration=0)
    gradient = rows.mean_gradients(theta, batch)
    policy = build_policy(engine.variants[0], run)
    for a in range(3):
        mine = batch.owner == a
        set_flat_params(policy, theta[a])
        coef = estimator_coefficients(
            run.algo.estimator, batch.rewards[:, mine], batch.alive[:, mine],  # type: ignore[arg-type]
            gamma=engine.gamma(a), baseline=run.algo.baseline,  # type: ignore[arg-type]
            reward_to_go=run.algo.reward_to_go, normalize=run.algo.normalize,  # type: ignore[arg-type]
        )  # fmt: skip
        reference = estimate_gradient(policy, batch.obs[:, mine], batch.actions[:, mine], coef)
        scale = float(reference.abs().max())
        assert scale > 0
        torch.testing.assert_close(gradient[a], reference, rtol=0, atol=2e-5 * scale)


# -- combinations that make no sense are one-line config errors --------------------------------


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["algo.estimator=reinforce", "algo.reward_to_go=from_step"], "algo.reward_to_go"),
        (["algo.estimator=reinforce", "algo.normalize=episode"], "algo.normalize"),
        (["algo.name=fedhpgvr", "algo.normalize=batch"], "algo.normalize"),
        (["algo=fedhpgvr", "algo.reward_to_go=from_step"], "algo.reward_to_go"),
        (["algo.normalize=everything"], "algo.normalize"),
        (["algo.reward_to_go=sometimes"], "algo.reward_to_go"),
    ],
)
def test_unsupported_combinations_name_their_key(overrides: list[str], key: str) -> None:
    with pytest.raises(ConfigError) as error:
        resolve_config(overrides=overrides)
    assert error.value.key == key


# -- the CartPole presets are the benchmarked set-up -------------------------------------------


@pytest.mark.parametrize(
    ("experiment", "batch_size"),
    [("k10_cartpole", 16), ("k10_cartpole_tuned", 1), ("k10_cartpole_stable", 2)],
)
def test_cartpole_presets_are_fedpgbrs_set_up(experiment: str, batch_size: int) -> None:
    """The keys benchmarks/estimator_options.py sets (BENCHMARKS.md's figures), composed."""
    run = resolve_config(overrides=[f"experiment={experiment}"])
    assert (run.env.family, run.env.level, run.env.gamma) == ("cartpole", 0.0, 0.999)
    assert run.agents.num_agents == 10
    assert run.agents.budget["batch_size"] == [batch_size]
    assert run.agents.budget["local_iters"] == [1]
    assert run.policy.hidden == [16, 16]
    assert (run.algo.estimator, run.algo.baseline) == ("gpomdp", "mean")
    assert (run.algo.reward_to_go, run.algo.normalize) == ("from_start", "none")
    assert (run.algo.optimizer, run.algo.step_size) == ("sgd", 1.0)
    assert run.strategy.name == "fedadam" and run.strategy.params["step_size"] == 0.01
    assert (run.eval.every, run.eval.episodes) == (2, 10)
