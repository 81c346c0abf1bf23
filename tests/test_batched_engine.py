"""The batched engines (common/batched/): the numpy engine's env and gradient, and for it and
the compiled engine, that an agent's numbers never depend on the company it is computed in."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fedhpg.common.batched import batched_group_or_none, unsupported
from fedhpg.common.batched.compiled import CompiledFedHPG
from fedhpg.common.batched.engine import BatchedFedHPG
from fedhpg.common.batched.maths import NUMPY
from fedhpg.common.batched.sampler import Batches, rollout
from fedhpg.common.group import WorkerLoopGroup, make_agent_group
from fedhpg.common.local import batch_gradient
from fedhpg.common.rollout import TrajectoryBatch
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import build_policy, get_flat_params, initial_theta
from fedhpg.envs.multi import CartPoleMulti, GroupedBatchEnv, make_multi_batch_env
from fedhpg.envs.registry import make_variants
from fedhpg.server.api import resolve_config

POPULATION = ["agents=population", "policy.hidden=[16,16]"]


ENGINES = {"numpy": BatchedFedHPG, "torch": BatchedFedHPG, "auto": CompiledFedHPG}
"""algo.engine → the engine it picks for CartPole."""


def _run(*overrides: str, family: str = "cartpole", agents: int = 9, engine: str = "numpy"):
    return resolve_config(
        overrides=[
            f"env={family}",
            f"agents.num_agents={agents}",
            *POPULATION,
            f"algo.engine={engine}",
            *overrides,
        ]
    )


def _group(run, indices) -> BatchedFedHPG | CompiledFedHPG:
    group = batched_group_or_none(run, variants_of(run, indices))
    expected = ENGINES[run.algo.engine]
    assert isinstance(group, expected), unsupported(run, variants_of(run, indices))
    return group


def test_cartpole_blocks_step_exactly_like_gymnasiums_vector_env_per_variant() -> None:
    variants = make_variants("cartpole", seed=3, num_agents=5, level=1.0)
    counts = [4, 8, 3, 8, 1]
    seeds = [11, 12, 13, 14, 15]
    multi = make_multi_batch_env(variants, counts)
    assert isinstance(multi, CartPoleMulti)
    singles = [v.make_batch_env(n) for v, n in zip(variants, counts, strict=True)]
    obs = multi.reset(seeds)
    assert np.array_equal(
        obs, np.concatenate([s.reset(seed=x) for s, x in zip(singles, seeds, strict=True)])
    )
    rng = np.random.default_rng(0)
    running = np.ones(multi.num_envs, dtype=bool)
    compared = 0
    for _ in range(200):
        actions = rng.integers(0, 2, multi.num_envs)
        step = multi.step(actions)
        refs = [
            s.step(actions[multi.offsets[i] : multi.offsets[i + 1]]) for i, s in enumerate(singles)
        ]
        ref_obs = np.concatenate([r.obs for r in refs])
        ref_end = np.concatenate([r.terminated | r.truncated for r in refs])
        # copies past their episode's end are the sampler's to ignore (gymnasium auto-resets)
        assert np.array_equal(step.obs[running], ref_obs[running])
        assert np.array_equal((step.terminated | step.truncated)[running], ref_end[running])
        compared += int(running.sum())
        running &= ~(step.terminated | step.truncated)
    assert compared > 200 and not running.any()


def test_a_family_without_a_native_batch_steps_block_by_block() -> None:
    variants = make_variants("acrobot", seed=0, num_agents=2, level=1.0)
    multi = make_multi_batch_env(variants, [2, 3])
    assert isinstance(multi, GroupedBatchEnv)
    assert multi.reset([1, 2]).shape == (5, 6)
    assert multi.step(np.zeros(5, dtype=np.int64)).obs.shape == (5, 6)


COUNTS = [5, 7, 6]


def _three_agents_away_from_the_start(run):
    """The engine of agents 0-2, a policy moved off the near-uniform start (so every layer
    matters), its stacked layers and one rollout of 5, 7 and 6 copies."""
    variants = variants_of(run, range(3))
    engine = _group(run, range(3))
    policy = build_policy(variants[0], run)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    theta = get_flat_params(policy).numpy()
    maths = engine.maths if isinstance(engine, BatchedFedHPG) else NUMPY
    layers = maths.unflatten(engine.shape, np.repeat(theta[None], 3, 0))
    env = make_multi_batch_env([variants[k] for k in range(3)], COUNTS)
    rngs = [np.random.default_rng(i) for i in range(3)]
    batches = rollout(env, layers, rngs, [500] * 3, maths=maths)
    return engine, policy, layers, batches


def _agent_batch(batches, a: int) -> TrajectoryBatch:
    """Agent a's copies of a rollout, as the loop's sampler would hand them over."""
    block = slice(batches.offsets[a], batches.offsets[a + 1])
    steps = batches.lengths[a]
    return TrajectoryBatch(
        obs=batches.obs[:steps, block],
        actions=batches.actions[:steps, block],
        log_probs=np.zeros((steps, COUNTS[a])),
        rewards=batches.rewards[:steps, block],
        alive=batches.alive[:steps, block],
        success=batches.success[block],
    )


@pytest.mark.parametrize("engine", ["numpy", "torch"])
@pytest.mark.parametrize("estimator", ["gpomdp", "reinforce"])
@pytest.mark.parametrize("baseline", ["mean", "none"])
def test_the_stacked_gradient_is_autograds_to_float32_rounding(estimator, baseline, engine) -> None:
    run = _run(f"algo.estimator={estimator}", f"algo.baseline={baseline}", agents=3, engine=engine)
    engine, policy, layers, batches = _three_agents_away_from_the_start(run)
    gradient = engine._gradient(Batches.of(batches), layers, [0, 1, 2])
    for a in range(3):
        batch = _agent_batch(batches, a)
        reference = batch_gradient(policy, batch, algo=run.algo, gamma=engine.gammas[a]).numpy()
        scale = np.abs(reference).max()
        assert scale > 0
        np.testing.assert_allclose(gradient[a], reference, rtol=0, atol=2e-5 * scale)


SETTINGS = [
    (),
    ("algo.optimizer=adam", "algo.step_size=0.01"),
    ("algo.grad_clip=0.5", "algo.estimator=reinforce"),
    ("algo.reward_to_go=from_step", "algo.normalize=batch"),
    ("algo.normalize=episode",),
]


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(
    "settings",
    SETTINGS,
    ids=["sgd", "adam", "clipped-reinforce", "from_step-normalize-batch", "normalize-episode"],
)
def test_an_agents_round_is_the_same_in_any_company(settings, engine) -> None:
    """Alone, in small groups, in another order, or all nine together: bit-identical θ_k and
    the same counts (the property that makes θ̃ independent of placement)."""
    run = _run(*settings, engine=engine)
    theta = initial_theta(variants_of(run, [0])[0], run)
    everyone = _group(run, range(9)).train(3, theta, list(range(9)))
    if settings and "grad_clip" in settings[0]:
        assert sum(r.stats.grad_clipped for r in everyone.values()) > 0, "clipping exercised"
    for company in ([4], [8, 0], [7, 2, 5], [6, 1, 3, 0, 8, 2, 4]):
        results = _group(run, company).train(3, theta, company)
        for k in company:
            assert torch.equal(results[k].theta, everyone[k].theta), (company, k)
            assert results[k].stats.env_steps == everyone[k].stats.env_steps
            assert results[k].stats.trajectories == everyone[k].stats.trajectories
            assert results[k].stats.train_return == everyone[k].stats.train_return


@pytest.mark.parametrize("engine", ENGINES)
def test_a_group_trains_a_subset_of_its_agents_as_their_own_groups_would(engine) -> None:
    run = _run(engine=engine)
    theta = initial_theta(variants_of(run, [0])[0], run)
    group = _group(run, range(9))
    chosen = group.train(1, theta, [1, 5, 6])
    alone = _group(run, [5]).train(1, theta, [5])
    assert set(chosen) == {1, 5, 6}
    assert torch.equal(chosen[5].theta, alone[5].theta)


@pytest.mark.parametrize("engine", ENGINES)
def test_agents_move_the_policy_and_count_their_work(engine) -> None:
    run = _run(engine=engine)
    theta = initial_theta(variants_of(run, [0])[0], run)
    group = _group(run, range(9))
    results = group.train(1, theta, list(range(9)))
    for k, result in results.items():
        budget = group.budget(k)
        assert result.stats.trajectories == budget.batch_size * budget.local_iters
        # CartPole pays 1 per step: the mean return is the mean episode length
        assert result.stats.train_return == result.stats.env_steps / result.stats.trajectories
        assert not torch.equal(result.theta, theta)
    assert len({tuple(r.theta[:8].tolist()) for r in results.values()}) == 9


@pytest.mark.parametrize("engine", ENGINES)
def test_evaluation_is_the_same_in_any_company_and_counts_episodes(engine) -> None:
    run = _run(engine=engine)
    theta = initial_theta(variants_of(run, [0])[0], run)
    everyone = _group(run, range(9)).evaluate(2, theta, 6, list(range(9)))
    alone = _group(run, [3]).evaluate(2, theta, 6, [3])
    assert alone[3] == everyone[3]
    for stats in everyone.values():
        assert stats.episodes == 6 and stats.return_mean == stats.length_mean >= 8


def test_runs_the_engine_does_not_cover_fall_back_to_the_loop() -> None:
    for overrides in (["algo=fedhpgvr"], ["algo.engine=loop"]):
        run = _run(*overrides)
        assert isinstance(make_agent_group(run, [0, 1]), WorkerLoopGroup)
    gridworld = resolve_config(overrides=["env=gridworld", *POPULATION, "agents.num_agents=2"])
    assert isinstance(make_agent_group(gridworld, [0, 1]), WorkerLoopGroup)
    assert unsupported(gridworld, variants_of(gridworld, [0])) is not None


@pytest.mark.parametrize("baseline", ["mean", "none"])
def test_bound_estimates_are_autograds_per_trajectory_ones(baseline) -> None:
    """algo.bound_estimates: the engine's σ̂², M̂ and ‖∇J‖² (per-trajectory gradients through
    its own kernel, a few agents per block) equal common.local.bound_statistics (torch vmap)
    on the same batches, to float32 rounding."""
    from fedhpg.common import batched
    from fedhpg.common.local import bound_statistics

    run = _run(f"algo.baseline={baseline}", "algo.bound_estimates=true", agents=3)
    engine, policy, layers, batches = _three_agents_away_from_the_start(run)
    all3 = np.ones(3, dtype=bool)
    floats = batched.engine.PER_TRAJECTORY_FLOATS
    try:  # blocks of one agent, then all three in one block: the same figures
        batched.engine.PER_TRAJECTORY_FLOATS = engine.shape.num_params * 7
        one_by_one = engine._bound_statistics(Batches.of(batches), layers, [0, 1, 2], all3)
    finally:
        batched.engine.PER_TRAJECTORY_FLOATS = floats
    together = engine._bound_statistics(Batches.of(batches), layers, [0, 1, 2], all3)
    skipping = engine._bound_statistics(
        Batches.of(batches), layers, [0, 1, 2], np.array([True, False, True])
    )
    assert skipping == [together[0], {}, together[2]]
    assert one_by_one == together
    for a in range(3):
        batch = _agent_batch(batches, a)
        reference = bound_statistics(policy, batch, algo=run.algo, gamma=engine.gammas[a])
        assert set(reference) == set(together[a]) and reference["bound_variance"] > 0
        for name, value in reference.items():
            assert together[a][name] == pytest.approx(value, rel=1e-4, abs=1e-6), name


@pytest.mark.parametrize("engine", ENGINES)
def test_bound_estimates_change_no_theta_and_no_company_changes_them(engine) -> None:
    plain = _run(engine=engine)
    measured = _run("algo.bound_estimates=true", engine=engine)
    theta = initial_theta(variants_of(plain, [0])[0], plain)
    before = _group(plain, range(9)).train(2, theta, list(range(9)))
    everyone = _group(measured, range(9)).train(2, theta, list(range(9)))
    names = ("bound_variance", "bound_second_moment", "bound_grad_norm_sq", "bound_smoothness")
    engine = _group(measured, range(9))
    for k in range(9):
        assert torch.equal(before[k].theta, everyone[k].theta)
        assert not set(names) & set(before[k].stats.algorithm)
        # the secant for L needs a second local iteration
        expected = names if engine.budget(k).local_iters > 1 else names[:3]
        assert set(expected) == set(everyone[k].stats.algorithm) & set(names), k
    assert any(engine.budget(k).local_iters > 1 for k in range(9))
    for company in ([4], [7, 2, 5]):
        results = _group(measured, company).train(2, theta, company)
        for k in company:
            mine = {n: v for n, v in results[k].stats.algorithm.items() if n in names}
            assert mine == {n: v for n, v in everyone[k].stats.algorithm.items() if n in names}
