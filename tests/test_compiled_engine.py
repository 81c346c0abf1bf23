"""The compiled engine (common/batched/compiled.py, kernels.py, streams.py, envs/compiled.py)
against independent references: numpy's random streams, gymnasium's CartPole constants and
the numpy CartPole batch, float64 tanh, torch autograd for every estimator option, and the
numpy engine's episode statistics. Company independence is in test_batched_engine.py (both
engines), placement through real processes in test_hosts.py."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import pytest
import torch
from oracle import TrajectoryBatch, batch_gradient, bound_statistics

from fedhpg.common.batched import batched_group_or_none, kernels
from fedhpg.common.batched.compiled import CompiledFedHPG, _RowBuffers
from fedhpg.common.batched.streams import agent_streams, next_double
from fedhpg.common.bounds import bound_stats, gradient_moments
from fedhpg.common.group import make_agent_group
from fedhpg.common.optim import AdamAscent
from fedhpg.common.policies import set_flat_params
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import Stream, build_policy, initial_theta
from fedhpg.envs.compiled import CARTPOLE_DEFAULTS, CARTPOLE_PHYSICS, cartpole_step, cartpole_table
from fedhpg.server.api import resolve_config

POPULATION = ["env=cartpole", "agents=population", "policy.hidden=[16,16]"]


def _run(*overrides: str, agents: int = 6):
    return resolve_config(overrides=[*POPULATION, f"agents.num_agents={agents}", *overrides])


def _engine(run, indices) -> CompiledFedHPG:
    group = batched_group_or_none(run, variants_of(run, indices))
    assert isinstance(group, CompiledFedHPG)
    return group


@pytest.mark.parametrize("seed", [0, 7, 123456789, 2**32 + 5, 2**40])
def test_agent_streams_are_numpys_default_rng(seed: int) -> None:
    """The kernels' PCG64 seeded through SeedSequence draws what default_rng([seed, k, round,
    purpose]) draws, including entropy words past 32 bits and past the pool of four, for
    agent indices of one word (seeded in one call) and past one word (one by one)."""
    one_word = [0, 1, 499, 9999, 2**31, 2**32 - 1]
    for agents, round_index, purpose in [
        (one_word, 0, 0),
        (one_word, 17, 1),
        (one_word, 2**40, 2),
        ([*one_word, 2**33 + 1], 100_000, 2),
    ]:
        streams = agent_streams(seed, agents, round_index, purpose)
        for row, k in enumerate(agents):
            ours = [next_double(streams[row]) for _ in range(64)]
            theirs = np.random.default_rng([seed, k, round_index, purpose]).random(64)
            assert np.array_equal(ours, theirs), (seed, k, round_index, purpose)


def test_tanh32_is_within_seven_ulps_of_tanh() -> None:
    """The float32 rational function (common/batched/kernels.py's docstring: every float32
    in [2⁻³⁰, 10.5] measured, at most 7 ulps off, 0.28 % three or more); a fixed sample of
    them here (the function is deterministic, so are its errors: the bounds are this
    sample's figures, rounded up). A coefficient 0.1 % off fails it."""
    rng = np.random.default_rng(0)
    magnitudes = np.concatenate(
        [
            rng.uniform(0, 1, 400_000),
            rng.uniform(1, 12, 400_000),
            np.exp(rng.uniform(-40, 0, 200_000)),
            [0.0, 1e-45, 2.0**-30, 9.0, 9.0109, 9.02, 10.0, 10.5, 1e30, 3.4e38],
        ]
    ).astype(np.float32)
    values = np.concatenate([magnitudes, -magnitudes])
    ours = np.array([kernels.tanh32(v) for v in values[:2000]], dtype=np.float32)
    ours = np.concatenate([ours, _tanh32_many(values[2000:])])
    exact = np.tanh(values.astype(np.float64)).astype(np.float32)
    ulps = np.abs(ours.view(np.int32).astype(np.int64) - exact.view(np.int32).astype(np.int64))
    assert ulps.max() <= 7
    assert (ulps > 2).mean() < 0.015  # 1.39 % in this sample
    assert (ulps > 0).mean() < 0.45  # 43 %: the sample is dense in [1, 12], where most are off
    assert np.array_equal(np.sign(ours), np.sign(exact))
    assert np.isnan(kernels.tanh32(np.float32("nan")))
    assert kernels.tanh32(np.float32("inf")) == 1.0 and kernels.tanh32(np.float32("-inf")) == -1.0


def _tanh32_many(values: np.ndarray) -> np.ndarray:
    from numba import njit

    @njit
    def many(x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        for i in range(len(x)):
            out[i] = kernels.tanh32(x[i])
        return out

    return many(values)  # type: ignore[no-any-return]


def test_cartpole_constants_are_gymnasiums() -> None:
    stock = gym.make("CartPole-v1").unwrapped
    assert tuple(float(getattr(stock, n)) for n in CARTPOLE_PHYSICS) == CARTPOLE_DEFAULTS


def test_cartpole_steps_exactly_like_gymnasium() -> None:
    """The compiled step and gymnasium's CartPoleEnv (both float64) from the same states and
    actions: the same floats and the same ends, for heterogeneous variants."""
    run = _run("env.level=1.0", agents=4)
    variants = [variants_of(run, [k])[k] for k in range(4)]
    physics = cartpole_table(variants)
    rng = np.random.default_rng(1)
    compared = 0
    for k, variant in enumerate(variants):
        env = variant.make_env().unwrapped
        env.reset(seed=k)
        state = np.asarray(env.state, dtype=np.float64)[None].copy()
        ended = False
        while not ended:
            action = int(rng.integers(0, 2))
            _, _, ended, _, _ = env.step(action)
            terminated = cartpole_step(state, 0, physics[k], action)
            assert np.array_equal(state[0], np.asarray(env.state, dtype=np.float64))
            assert terminated == ended
            compared += 1
    assert compared > 50


@dataclass
class Sampled:
    """One local iteration's sampling through the kernel, laid out as train() lays it out."""

    engine: CompiledFedHPG
    order: list[int]
    batch: np.ndarray
    gammas: np.ndarray
    physics: np.ndarray
    thetas: np.ndarray
    rows: _RowBuffers
    span: np.ndarray
    copy_start: np.ndarray
    lengths: np.ndarray

    def trajectories(self, a: int) -> TrajectoryBatch:
        """Agent a's rows as the loop's sampler hands a batch over (time-major, padded)."""
        count = int(self.batch[a])
        first = int(self.copy_start[a])
        steps = int(self.lengths[first : first + count].max())
        obs = np.zeros((steps, count, 4), dtype=np.float32)
        actions = np.zeros((steps, count), dtype=np.int64)
        alive = np.zeros((steps, count), dtype=bool)
        for r in range(self.span[a, 0], self.span[a, 1]):
            t, c = self.rows.time[r], self.rows.copy[r]
            obs[t, c], actions[t, c], alive[t, c] = self.rows.obs[r], self.rows.action[r], True
        return TrajectoryBatch(
            obs=obs,
            actions=actions,
            log_probs=np.zeros((steps, count)),
            rewards=alive.astype(np.float64),
            alive=alive,
            success=np.zeros(count, dtype=bool),
        )


def _sample(run, indices, theta, round_index=0) -> Sampled:
    engine = _engine(run, indices)
    order = sorted(indices)
    batch = np.array([engine.budget(k).batch_size for k in order], dtype=np.int64)
    horizons, gammas, physics = engine._per_agent(order)
    streams = agent_streams(run.seed, order, round_index, int(Stream.TRAIN))
    thetas = np.repeat(theta.numpy()[None], len(order), 0)
    rows = _RowBuffers(int((batch * np.minimum(horizons, 500)).sum()), 4)
    span = np.zeros((len(order), 2), dtype=np.int64)
    copy_start = np.zeros(len(order), dtype=np.int64)
    lengths = np.zeros(int(batch.sum()), dtype=np.int64)
    kernels.sample_iteration(thetas, engine.sizes, physics, batch, horizons, gammas, streams,
                             np.arange(len(order)), rows.obs, rows.action, rows.copy, rows.time,
                             span, copy_start, lengths, np.zeros(int(batch.sum())))  # fmt: skip
    return Sampled(engine, order, batch, gammas, physics, thetas, rows, span, copy_start, lengths)


def _away_from_the_start(run):
    policy = build_policy(variants_of(run, [0])[0], run)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    return policy, torch.nn.utils.parameters_to_vector(policy.parameters()).detach()


def test_sampling_draws_from_the_agents_stream_in_the_documented_order() -> None:
    """Replayed in Python from numpy's Generator: the initial states (uniform(±0.05, (4, B)),
    gymnasium's draw), one uniform per running copy per step in copy order, the kernel's own
    forward and inverse-CDF draw, and the numpy CartPole batch's dynamics: every row, every
    action and every episode length of the kernel's sample."""
    run = _run(agents=3)
    _, theta = _away_from_the_start(run)
    sampled = _sample(run, [0, 1, 2], theta, round_index=4)
    engine, rows, span = sampled.engine, sampled.rows, sampled.span
    forward_w, _ = kernels.padded_weights(sampled.thetas[0], engine.sizes)
    for a, k in enumerate(sampled.order):
        count = int(sampled.batch[a])
        rng = np.random.default_rng([run.seed, k, 4, int(Stream.TRAIN)])
        state = rng.uniform(-0.05, 0.05, size=(4, count)).T.copy()
        running = list(range(count))
        row = int(span[a, 0])
        t = 0
        while running:
            obs = state[running].astype(np.float32)
            even = np.zeros((count, 16), dtype=np.float32)
            odd = np.zeros((count, 16), dtype=np.float32)
            in_even = kernels.forward(forward_w, engine.sizes, obs, even, odd, len(running))
            logits = even if in_even else odd
            still = []
            for slot, c in enumerate(running):
                action = kernels.draw_action(logits, slot, 2, rng.random(), np.zeros(2, np.float32))
                assert (rows.time[row], rows.copy[row], rows.action[row]) == (t, c, action)
                assert np.array_equal(rows.obs[row], obs[slot])
                row += 1
                if cartpole_step(state, c, sampled.physics[a], action) or t + 1 >= 500:
                    assert sampled.lengths[sampled.copy_start[a] + c] == t + 1
                else:
                    still.append(c)
            running = still
            t += 1
        assert row == span[a, 1]


def test_the_kernels_forward_is_torchs_policy() -> None:
    run = _run(agents=1)
    policy, theta = _away_from_the_start(run)
    engine = _engine(run, [0])
    obs = np.random.default_rng(0).normal(0, 1, (50, 4)).astype(np.float32)
    forward_w, _ = kernels.padded_weights(theta.numpy(), engine.sizes)
    even, odd = np.zeros((50, 16), np.float32), np.zeros((50, 16), np.float32)
    logits = even if kernels.forward(forward_w, engine.sizes, obs, even, odd, 50) else odd
    with torch.no_grad():
        reference = policy.net(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(logits[:, :2], reference, rtol=0, atol=2e-6)


@pytest.mark.parametrize("hidden", [[16, 16], [], [8, 12, 8], [20, 5]])
def test_the_lanes_forward_gives_the_row_forwards_numbers(hidden: list[int]) -> None:
    """The sampler's two forwards, row by row (fewer than LANES_FROM copies running) and as
    lanes (from it on), give the same numbers for any count of columns, so the switch never
    changes an episode."""
    sizes = np.array([4, *hidden, 2], dtype=np.int64)
    rng = np.random.default_rng(len(hidden))
    count = sum(int(a) * int(b) + int(b) for a, b in itertools.pairwise(sizes))
    theta = (rng.standard_normal(count) * 0.7).astype(np.float32)
    forward_w, _ = kernels.padded_weights(theta, sizes)
    width, lanes = forward_w.shape[2], kernels.LANES
    for columns in (1, 5, 12, 16, 17, 40):
        obs = (rng.standard_normal((columns, 4)) * 2).astype(np.float32)
        even, odd = np.zeros((columns, width), np.float32), np.zeros((columns, width), np.float32)
        rows = even if kernels.forward(forward_w, sizes, obs, even, odd, columns) else odd
        chunks = -(-columns // lanes)
        first = np.zeros((chunks, width, lanes), np.float32)
        for c in range(columns):
            first[c // lanes, :4, c % lanes] = obs[c]
        even_l, odd_l = np.zeros_like(first), np.zeros_like(first)
        in_even = kernels.forward_lanes(forward_w, sizes, first, even_l, odd_l, columns)
        out = even_l if in_even else odd_l
        got = np.stack([out[c // lanes, :2, c % lanes] for c in range(columns)])
        assert np.array_equal(got, rows[:, :2]), (hidden, columns)


SETTINGS = [
    ("algo.estimator=gpomdp", "algo.baseline=mean"),
    ("algo.estimator=gpomdp", "algo.baseline=none"),
    ("algo.estimator=reinforce", "algo.baseline=mean"),
    ("algo.estimator=reinforce", "algo.baseline=none"),
    ("algo.reward_to_go=from_step",),
    ("algo.reward_to_go=from_step", "algo.normalize=batch"),
    ("algo.normalize=episode",),
    ("algo.normalize=batch", "algo.estimator=reinforce"),
]


@pytest.mark.parametrize("settings", SETTINGS, ids=["-".join(s) for s in SETTINGS])
def test_the_gradient_and_bound_figures_are_autograds(settings) -> None:
    """For each estimator option: the kernel's batch gradient (before clipping and the step)
    and its per-trajectory moments equal common/local.py's torch autograd on the same
    trajectories, to float32 rounding; and θ moves by step · gradient."""
    run = _run(*settings, "env.gamma=0.97", agents=3)
    policy, theta = _away_from_the_start(run)
    sampled = _sample(run, [0, 1, 2], theta)
    engine, batch, gammas, thetas, rows = (
        sampled.engine, sampled.batch, sampled.gammas, sampled.thetas, sampled.rows,
    )  # fmt: skip
    before = thetas.copy()
    measure = np.ones(3, dtype=np.bool_)
    per_trajectory = np.zeros((int(batch.sum()), len(theta)), dtype=np.float32)
    trajectory_start = np.concatenate([[0], np.cumsum(batch)[:-1]]).astype(np.int64)
    unclipped = np.zeros((3, len(theta)), dtype=np.float32)
    kernels.learn_iteration(thetas, np.zeros_like(thetas), np.zeros_like(thetas), engine.sizes,
                            batch, gammas, np.zeros(3, dtype=np.int64), np.arange(3), rows.obs,
                            rows.action, rows.copy, rows.time, rows.coef, sampled.span,
                            sampled.copy_start, sampled.lengths, engine.options, 0.5, -1.0,
                            np.zeros(3, dtype=np.bool_),
                            measure, per_trajectory, trajectory_start, unclipped)  # fmt: skip
    set_flat_params(policy, theta)
    for a in range(3):
        trajectories = sampled.trajectories(a)
        reference = batch_gradient(policy, trajectories, algo=run.algo, gamma=gammas[a]).numpy()
        scale = np.abs(reference).max()
        assert scale > 0
        np.testing.assert_allclose(unclipped[a], reference, rtol=0, atol=2e-5 * scale)
        step = (thetas[a].astype(np.float64) - before[a]) / 0.5
        np.testing.assert_allclose(step, unclipped[a], rtol=0, atol=1e-4 * scale)
        if batch[a] >= 2:
            moments = bound_statistics(policy, trajectories, algo=run.algo, gamma=gammas[a])
            first = int(trajectory_start[a])
            rows_a = torch.from_numpy(per_trajectory[first : first + int(batch[a])].copy())
            ours = bound_stats(gradient_moments(rows_a))
            for name, value in moments.items():
                assert ours[name] == pytest.approx(value, rel=1e-4, abs=1e-6), name


def test_adam_and_clipping_are_the_engines_steps() -> None:
    """The kernel's Adam is the engine's (common/optim.py's rows of Adams), step by step."""
    rng = np.random.default_rng(3)
    theta = rng.normal(0, 1, 50).astype(np.float32)
    adam = AdamAscent(0.01)
    reference = torch.from_numpy(theta.copy()).unsqueeze(0)
    ours = theta.copy()
    our_first, our_second = np.zeros(50, np.float32), np.zeros(50, np.float32)
    for done in range(4):
        gradient = rng.normal(0, 1, 50).astype(np.float32)
        reference += adam.direction(torch.from_numpy(gradient).unsqueeze(0))
        kernels.ascend(ours, gradient, our_first, our_second, 1, 0.01, done)
        np.testing.assert_allclose(ours, reference[0].numpy(), rtol=1e-6, atol=1e-7)
    run = _run("algo.grad_clip=0.5", "algo.optimizer=sgd", "algo.step_size=1.0", agents=4)
    start = initial_theta(variants_of(run, [0])[0], run)
    engine = _engine(run, range(4))
    results = engine.train(0, start, list(range(4)))
    for k, result in results.items():
        iterations = engine.budget(k).local_iters
        assert result.stats.grad_clipped == iterations  # the initial gradients are larger
        assert float((result.theta - start).norm()) <= 0.5 * iterations + 1e-5


def test_episode_statistics_match_the_torch_engine() -> None:
    """The same θ̃_0 and population, 300 agents: the compiled backend's and the torch engine's
    mean training episode length agree within four standard errors (their random numbers
    differ, their distributions must not)."""
    run = _run(agents=300)
    theta = initial_theta(variants_of(run, [0])[0], run)
    lengths = {}
    for engine in ("auto", "torch"):
        engine_run = _run(f"algo.engine={engine}", agents=300)
        group = make_agent_group(engine_run, list(range(300)))
        results = group.train(0, theta, list(range(300)))
        per_episode = [r.stats.train_return for r in results.values()]
        lengths[engine] = (np.mean(per_episode), np.std(per_episode) / math.sqrt(300))
    (ours, se_ours), (theirs, se_theirs) = lengths["auto"], lengths["torch"]
    assert abs(ours - theirs) < 4 * math.hypot(se_ours, se_theirs), lengths


def test_a_round_cut_into_parts_of_agents_is_the_same_round(monkeypatch) -> None:
    """Buffers too small for all the agents' rows at once: the iteration runs in parts, and
    every θ, count and bound figure is what one pass gives."""
    from fedhpg.common.batched import compiled

    run = _run("algo.bound_estimates=true", agents=7)
    theta = initial_theta(variants_of(run, [0])[0], run)
    whole = _engine(run, range(7)).train(2, theta, list(range(7)))
    monkeypatch.setattr(compiled, "MAX_ROWS", 1)  # parts the size of the largest agent's rows
    parts = _engine(run, range(7)).train(2, theta, list(range(7)))
    for k in range(7):
        assert torch.equal(parts[k].theta, whole[k].theta)
        mine, theirs = parts[k].stats, whole[k].stats
        assert (mine.env_steps, mine.train_return) == (theirs.env_steps, theirs.train_return)
        bound = {n: v for n, v in mine.algorithm.items() if n.startswith("bound_")}
        assert bound and bound == {n: v for n, v in theirs.algorithm.items() if n in bound}


@pytest.mark.parametrize("hidden", [[], [8, 12, 8]], ids=["linear", "three-layers"])
def test_any_number_of_hidden_layers(hidden: list[int]) -> None:
    """A linear softmax policy and three hidden layers of different widths: the forward is
    torch's and the gradient autograd's, as with the 16-16 MLP of the other tests."""
    run = _run(f"policy.hidden={hidden}", agents=2)
    policy, theta = _away_from_the_start(run)
    sampled = _sample(run, [0, 1], theta)
    engine = sampled.engine
    obs = np.random.default_rng(1).normal(0, 1, (9, 4)).astype(np.float32)
    forward_w, _ = kernels.padded_weights(theta.numpy(), engine.sizes)
    width = forward_w.shape[2]
    even, odd = np.zeros((9, width), np.float32), np.zeros((9, width), np.float32)
    logits = even if kernels.forward(forward_w, engine.sizes, obs, even, odd, 9) else odd
    with torch.no_grad():
        reference = policy.net(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(logits[:, :2], reference, rtol=0, atol=2e-6)
    unclipped = np.zeros((2, len(theta)), dtype=np.float32)
    thetas = sampled.thetas
    kernels.learn_iteration(thetas, np.zeros_like(thetas), np.zeros_like(thetas), engine.sizes,
                            sampled.batch, sampled.gammas, np.zeros(2, dtype=np.int64),
                            np.arange(2), sampled.rows.obs, sampled.rows.action,
                            sampled.rows.copy, sampled.rows.time, sampled.rows.coef,
                            sampled.span, sampled.copy_start, sampled.lengths, engine.options,
                            1.0, -1.0, np.zeros(2, dtype=np.bool_), np.ones(2, dtype=np.bool_),
                            np.zeros((int(sampled.batch.sum()), len(theta)), np.float32),
                            np.concatenate([[0], np.cumsum(sampled.batch)[:-1]]),
                            unclipped)  # fmt: skip
    for a in range(2):
        gamma = sampled.gammas[a]
        reference = batch_gradient(policy, sampled.trajectories(a), algo=run.algo, gamma=gamma)
        scale = np.abs(reference.numpy()).max()
        np.testing.assert_allclose(unclipped[a], reference.numpy(), rtol=0, atol=2e-5 * scale)


def test_the_engines_columns_are_its_per_agent_results() -> None:
    """What an agent host sends (the round as columns) and what a one-agent process or the
    in-process pool reads (one LocalResult and one hook call per agent and iteration) are the
    same numbers: the columns gathered from the per-agent path equal the engine's own, but
    for the CPU times measured on the way."""
    from fedhpg.common.round_columns import gathered, train_columns

    run = _run("algo.bound_estimates=true", agents=9)
    theta = initial_theta(variants_of(run, [0])[0], run)
    agents = [0, 2, 3, 5, 6, 8]
    own = train_columns(_engine(run, range(9)), 3, theta, agents)
    works: list[list] = []

    def hook(k: int, work) -> None:
        while len(works) <= work.iteration:
            works.append([])
        works[work.iteration].append((agents.index(k), work))

    results = _engine(run, range(9)).train(3, theta, agents, on_iteration=hook)
    theirs = gathered(agents, [results[k] for k in agents], works)
    assert own.agents == theirs.agents == agents
    assert np.array_equal(own.thetas, theirs.thetas)
    for name in ("trajectories", "env_steps", "train_return", "grad_clipped"):
        assert getattr(own, name).tolist() == getattr(theirs, name).tolist(), name
    measured = {"engine_sample_s", "engine_gradient_s"}
    assert set(own.algorithm) == set(theirs.algorithm) > measured
    for name in set(own.algorithm) - measured:
        assert own.algorithm[name] == theirs.algorithm[name], name
    assert (
        len(own.iterations)
        == len(theirs.iterations)
        == max(_engine(run, range(9)).budget(k).local_iters for k in agents)
    )
    for mine, their in zip(own.iterations, theirs.iterations, strict=True):
        assert mine.positions.tolist() == their.positions.tolist()
        assert mine.env_steps.tolist() == their.env_steps.tolist() == mine.grad_steps.tolist()
    assert [own.record(i).env_steps for i in range(6)] == [
        results[k].stats.env_steps for k in agents
    ]


GRADIENT_PROBE = """
import hashlib
import numpy as np
from numba import njit
from fedhpg.common.batched import kernels


@njit(cache=True, error_model="numpy")
def call(theta, sizes, obs, action, coef, out):  # a caller without fastmath, as learn_iteration
    kernels.score_gradient(theta, sizes, obs, action, coef, 0, len(coef), out,
                           kernels.gradient_workspace(sizes))


sizes = np.array([4, 16, 16, 2], dtype=np.int64)
d = sum(int(sizes[i] * sizes[i + 1] + sizes[i + 1]) for i in range(len(sizes) - 1))
rng = np.random.default_rng(0)
theta = (rng.standard_normal(d) * 0.5).astype(np.float32)
obs = rng.standard_normal((1000, 4)).astype(np.float32)
action = rng.integers(0, 2, 1000).astype(np.int64)
coef = rng.standard_normal(1000).astype(np.float32)
out = np.zeros(d, dtype=np.float32)
call(theta, sizes, obs, action, coef, out)
print(hashlib.sha256(out.tobytes()).hexdigest())
"""


def test_a_gradient_just_compiled_is_the_one_loaded_from_the_cache(tmp_path) -> None:
    """A process that compiles the kernels and one that loads them from numba's cache must
    round the gradient alike, or θ̃ would depend on which process compiled (placement, resume).
    With ``nsz``/``arcp`` among the gradient's fastmath flags they did not."""
    import os
    import subprocess
    import sys

    probe = tmp_path / "gradient_probe.py"
    probe.write_text(GRADIENT_PROBE)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}
    compiled, cached = (
        subprocess.run(
            [sys.executable, str(probe)], env=env, capture_output=True, text=True, check=True,
            timeout=300,
        ).stdout.strip()
        for _ in range(2)
    )  # fmt: skip
    assert (tmp_path / "cache").exists(), "the first run wrote numba's cache"
    assert compiled == cached
