"""The compiled backend (common/learning/batched/backend.py, kernels.py, envs/compiled.py) against
independent references: the engine's own random draws (common/learning/randomness.py), gymnasium's
CartPole constants and dynamics, float64 tanh, torch's policy and autograd for every
estimator option, and the torch engine's episode statistics. Company independence through
real processes is in test_hosts.py, for every algorithm."""

from __future__ import annotations

import itertools
import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.batched import compiled_agents, compiled_backend, kernels
from fedhpg.common.learning.batched.backend import CompiledBackend
from fedhpg.common.learning.batched.mlp import MLPShape
from fedhpg.common.learning.engine.backend import Draws
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.estimators import estimate_gradient, estimator_coefficients
from fedhpg.common.learning.group import EngineGroup, SplitGroup, make_agent_group
from fedhpg.common.learning.policies import set_flat_params
from fedhpg.common.learning.randomness import Purpose, trajectory_keys, uniforms, uniforms64
from fedhpg.common.learning.worker import build_policy, initial_theta
from fedhpg.envs.compiled import CARTPOLE_DEFAULTS, CARTPOLE_PHYSICS, cartpole_step, cartpole_table
from fedhpg.server.commands.api import resolve_config

POPULATION = ["env=cartpole", "agents=population", "policy.hidden=[16,16]"]


def _run(*overrides: str, agents: int = 6):
    return resolve_config(overrides=[*POPULATION, f"agents.num_agents={agents}", *overrides])


def _engine(run, indices) -> Engine:
    variants = variants_of(run, indices)
    assert compiled_agents(run, variants) == set(indices)
    return Engine(run, variants, backend=compiled_backend)


def _away_from_the_start(run):
    policy = build_policy(variants_of(run, [0])[0], run)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    return policy, torch.nn.utils.parameters_to_vector(policy.parameters()).detach()


def test_the_kernels_draw_the_engines_numbers() -> None:
    """The compiled hash is common/learning/randomness.py's: the same uniforms, bit for bit, for
    keys and counters of every sign."""
    keys = trajectory_keys(3, torch.arange(40), 7, Purpose.TRAIN, 2, torch.arange(40) % 5)
    for counter in (-4, -1, 0, 1, 499, 2**31):
        ours24 = np.array([kernels.uniform24(int(k), counter) for k in keys.tolist()])
        ours53 = np.array([kernels.uniform53(int(k), counter) for k in keys.tolist()])
        assert np.array_equal(ours24, uniforms(keys, counter).numpy()), counter
        assert np.array_equal(ours53, uniforms64(keys, counter).numpy()), counter


def test_the_compiled_keys_are_the_engines_words() -> None:
    generator = torch.Generator().manual_seed(3)
    agents = torch.randint(0, 10**6, (40,), generator=generator)
    counts = torch.randint(0, 9, (40,), generator=generator)  # a row of none included
    owner = torch.repeat_interleave(torch.arange(40), counts)
    index = torch.arange(int(counts.sum())) - (torch.cumsum(counts, 0) - counts)[owner]
    settings = [(0, 0, 0, Purpose.TRAIN), (2**40 + 7, 10**6, 9, Purpose.EVALUATE),
                (5, 3, 1, Purpose.SERVER)]  # fmt: skip
    backend = CompiledBackend(MLPShape((4, 2)))
    for seed, round_index, iteration, purpose in settings:
        expected = trajectory_keys(seed, agents, round_index, purpose, iteration, index, owner)
        got = backend.keys(Draws(seed, agents, round_index, purpose, iteration), counts)
        assert torch.equal(got, expected)
    assert not torch.equal(
        backend.keys(Draws(0, agents, 0, Purpose.TRAIN, 1), counts),
        backend.keys(Draws(0, agents, 0, Purpose.TRAIN, 0), counts),
    ), "an iteration's keys are its own"


def test_tanh32_is_within_seven_ulps_of_tanh() -> None:
    """The float32 rational function (common/learning/batched/kernels.py's docstring: every float32
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


def test_sampling_draws_from_each_copys_key_in_the_documented_order() -> None:
    """Replayed in Python: each copy's start from its key's counters −1 … −4, one decision a
    step from counter t, the kernel's own forward and inverse-CDF draw, gymnasium's dynamics:
    every step, action and episode length of the backend's sample."""
    run = _run(agents=3)
    _, theta = _away_from_the_start(run)
    engine = _engine(run, [0, 1, 2])
    rows = engine.begin(4, theta, [0, 1, 2])
    counts = torch.tensor([3, 1, 4])
    batch = rows.sample(rows.theta, counts, iteration=1)
    sizes = engine.backend.sizes  # type: ignore[attr-defined]
    forward_w, _ = kernels.padded_weights(theta.numpy(), sizes)
    owner = batch.owner.tolist()
    index = [owner[:n].count(owner[n]) for n in range(len(owner))]
    keys = trajectory_keys(run.seed, torch.tensor(owner), 4, Purpose.TRAIN, 1, torch.tensor(index))
    physics = cartpole_table([engine.variants[k] for k in range(3)])
    for n in range(len(owner)):
        key = int(keys[n])
        state = np.array([[kernels.uniform53(key, -1 - i) * 0.1 - 0.05 for i in range(4)]])
        t = 0
        while True:
            obs = state.astype(np.float32)
            acts = np.zeros((3, 1, kernels.padded_width(sizes)), np.float32)
            acts[kernels.INPUTS, :, :4] = obs
            kernels.forward(forward_w, sizes, acts, 1)
            draw = kernels.uniform24(key, t)
            action = kernels.draw_action(acts, 0, 2, draw, np.zeros(2, np.float32))
            assert bool(batch.alive[t, n])
            assert np.array_equal(batch.obs[t, n].numpy(), obs[0])
            assert int(batch.actions[t, n]) == action
            ended = cartpole_step(state, 0, physics[owner[n]], action)
            t += 1
            if ended or t >= 500:
                break
        assert int(batch.alive[:, n].sum()) == t


def test_the_backends_returns_are_the_sums_of_its_rewards() -> None:
    """The returns the backend hands over with a batch (a reward of 1 a step) are the bits
    the batch's own sums give, undiscounted and discounted."""
    run = _run(agents=3)
    _, theta = _away_from_the_start(run)
    engine = _engine(run, [0, 1, 2])
    rows = engine.begin(4, theta, [0, 1, 2])
    batch = rows.sample(rows.theta, torch.tensor([3, 1, 4]), iteration=1)
    assert batch._returns is not None
    rewards, _ = batch.cells
    summed = batch.layout.column_totals(rewards)
    assert torch.equal(batch.returns(), summed) and bool((summed > 1).any())
    assert torch.equal(summed, batch.rewards.sum(dim=0))
    assert not torch.equal(batch.returns(rows.gammas), summed)  # discounted: summed here


def test_the_kernels_forward_is_torchs_policy() -> None:
    run = _run(agents=1)
    policy, theta = _away_from_the_start(run)
    sizes = CompiledBackend(_shape(run)).sizes
    obs = np.random.default_rng(0).normal(0, 1, (50, 4)).astype(np.float32)
    forward_w, _ = kernels.padded_weights(theta.numpy(), sizes)
    acts = np.zeros((3, 50, kernels.padded_width(sizes)), np.float32)
    acts[kernels.INPUTS, :, :4] = obs
    kernels.forward(forward_w, sizes, acts, 50)
    logits = acts[0]
    with torch.no_grad():
        reference = policy.net(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(logits[:, :2], reference, rtol=0, atol=2e-6)


def _shape(run):
    from fedhpg.common.learning.batched import mlp_shape

    return mlp_shape(build_policy(variants_of(run, [0])[0], run))


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
        acts = np.zeros((3, columns, width), np.float32)
        acts[kernels.INPUTS, :, :4] = obs
        kernels.forward(forward_w, sizes, acts, columns)
        rows = acts[0]
        chunks = -(-columns // lanes)
        slots = np.zeros((3, chunks, width, lanes), np.float32)
        for c in range(columns):
            slots[kernels.INPUTS, c // lanes, :4, c % lanes] = obs[c]
        kernels.forward_lanes(forward_w, sizes, slots, columns)
        got = np.stack([slots[0, c // lanes, :2, c % lanes] for c in range(columns)])
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
@pytest.mark.parametrize("hidden", [[16, 16], [], [8, 12, 8]])
def test_the_gradients_are_autograds(settings, hidden) -> None:
    """For each estimator option and architecture: the backend's per-row gradient of its own
    sample equals the per-agent autograd oracle's on that row's trajectories, to float32
    rounding (rows of 4, 1 and 6 trajectories side by side)."""
    run = _run(*settings, "env.gamma=0.97", f"policy.hidden={hidden}", agents=3)
    policy, theta = _away_from_the_start(run)
    engine = _engine(run, [0, 1, 2])
    rows = engine.begin(2, theta, [0, 1, 2])
    batch = rows.sample(rows.theta, torch.tensor([4, 1, 6]), iteration=0)
    gradient = rows.mean_gradients(rows.theta, batch)
    set_flat_params(policy, theta)
    references = []
    for a in range(3):
        mine = batch.owner == a
        coef = estimator_coefficients(
            run.algo.estimator, batch.rewards[:, mine], batch.alive[:, mine],  # type: ignore[arg-type]
            gamma=engine.gamma(a), baseline=run.algo.baseline,  # type: ignore[arg-type]
            reward_to_go=run.algo.reward_to_go, normalize=run.algo.normalize,  # type: ignore[arg-type]
        )  # fmt: skip
        obs, actions = batch.obs[:, mine], batch.actions[:, mine]
        references.append(estimate_gradient(policy, obs, actions, coef))
    # A row of one trajectory has a zero gradient under a baseline or batch normalisation;
    # the tolerance is float32 rounding of the largest gradient in the batch.
    scale = max(float(r.abs().max()) for r in references)
    assert scale > 0
    for a, reference in enumerate(references):
        torch.testing.assert_close(gradient[a], reference, rtol=0, atol=2e-5 * scale)


def test_every_algorithm_runs_on_the_backend() -> None:
    """FedHPG, FedHPGVR and FedPG-BR on CartPole: their honest agents get an engine on the
    compiled backend, a sampling attacker one on torch beside it."""
    for algo in (["algo=fedhpg"], ["algo=fedhpgvr"], ["algo=fedpgbr", "strategy=fedpgbr"]):
        run = _run(*algo, "attack=random_action", "attack.agents=[1]", agents=3)
        group = make_agent_group(run, [0, 1, 2])
        assert isinstance(group, SplitGroup)
        compiled, torch_part = group.parts
        assert isinstance(compiled, EngineGroup) and isinstance(
            compiled.engine.backend, CompiledBackend
        )
        assert list(compiled.indices) == [0, 2] and list(torch_part.indices) == [1]
        results = group.train(1, initial_theta(variants_of(run, [0])[0], run), [0, 1, 2]).result
        # The attacker's θ may leave the reals under FedHPGVR (uniform actions the policy
        # gives ~0 probability make the importance weights overflow); the server drops it.
        assert results.agents == [0, 1, 2]
        assert all(np.isfinite(results.theta_of(a)).all() for a in (0, 2)), algo


@pytest.mark.parametrize(
    "algo",
    [
        ["algo=fedhpg", "agents.budget.local_iters=[3]"],
        ["algo=fedhpgvr", "agents.budget.inner_steps=[3]"],
    ],
)
def test_an_algorithm_holds_one_batch_at_a_time(algo: list[str]) -> None:
    """The memory plan counts one batch per agent at a time: each algorithm lets its batch
    go before it samples the next, so the sampler reuses one set of row buffers for a whole
    round of several iterations instead of holding two. FedHPG's batches are drawn with their
    gradients a few agents at a time, into no row buffers at all."""
    run = _run(*algo, agents=3)
    group = make_agent_group(run, [0, 1, 2])
    assert isinstance(group, EngineGroup) and isinstance(group.engine.backend, CompiledBackend)
    theta = initial_theta(variants_of(run, [0])[0], run)
    for round_index in (1, 2):
        group.train(round_index, theta, [0, 1, 2])
    held = len(group.engine.backend._buffers.sets)  # type: ignore[attr-defined]
    assert held == (0 if algo[0] == "algo=fedhpg" else 1)


def test_episode_statistics_match_the_torch_engine() -> None:
    """The same θ̃_0 and population, 300 agents: the compiled backend's and the torch engine's
    mean training episode length agree within four standard errors (their floats differ,
    their distributions must not)."""
    run = _run(agents=300)
    theta = initial_theta(variants_of(run, [0])[0], run)
    lengths = {}
    for engine in ("auto", "torch"):
        engine_run = _run(f"algo.engine={engine}", agents=300)
        group = make_agent_group(engine_run, list(range(300)))
        assert (engine == "auto") == (isinstance(group.engine.backend, CompiledBackend))  # type: ignore[attr-defined]
        results = group.train(0, theta, list(range(300))).result
        per_episode = results.stats.train_return
        lengths[engine] = (np.mean(per_episode), np.std(per_episode) / math.sqrt(300))
    (ours, se_ours), (theirs, se_theirs) = lengths["auto"], lengths["torch"]
    assert abs(ours - theirs) < 4 * math.hypot(se_ours, se_theirs), lengths


GRADIENT_PROBE = """
import hashlib
import numpy as np
from numba import njit
from fedhpg.common.learning.batched import kernels


@njit(cache=True, error_model="numpy")
def call(theta, sizes, obs, action, coef, out):  # a caller without fastmath, as row_gradients
    kernels.score_gradient(theta, sizes, obs, action, coef, np.arange(len(coef)), 0, len(coef),
                           out, kernels.gradient_workspace(sizes))


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


@pytest.mark.slow
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
