"""The compiled backend's fused calls (common/learning/batched/fused.py) against their
definitions: a sample drawn with its keys in one call is the sample the separate key and
sampling kernels give, and a batch's mean-gradient sums in one call are
:func:`~fedhpg.common.learning.engine.backend.defined_mean_gradients` (the backend's own
coefficients and gradients, one call each, which test_compiled_engine.py and
test_compiled_estimator.py hold to gymnasium, autograd and the torch estimator), bit for bit:
random rows, budgets, horizons, discounts and θ, every estimator option (standardised ones
take the composed path), importance weights, rows that sample nothing, and every algorithm's
round end to end."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.batched import compiled_agents, compiled_backend, fused, kernels
from fedhpg.common.learning.batched.backend import CompiledBackend
from fedhpg.common.learning.engine.backend import Draws, defined_mean_gradients
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.learning.randomness import Purpose
from fedhpg.envs.compiled import CARTPOLE_STEP_LIMIT
from fedhpg.server.commands.api import resolve_config

AGENTS = 7
PARAMS = (4 * 16 + 16) + (16 * 16 + 16) + (16 * 2 + 2)
OPTIONS = [
    EstimatorOptions(estimator=estimator, baseline=baseline, reward_to_go=to_go,
                     normalize=normalize)  # type: ignore[arg-type]
    for estimator, baseline, to_go, normalize in itertools.product(
        ("gpomdp", "reinforce"), ("none", "mean"), ("from_start", "from_step"),
        ("none", "batch", "episode"),
    )
    if not (estimator == "reinforce" and to_go == "from_step")
]  # fmt: skip


@pytest.fixture(scope="module")
def backend() -> CompiledBackend:
    run = resolve_config(overrides=["env=cartpole", "agents=population", "policy.hidden=[16,16]",
                                    f"agents.num_agents={AGENTS}"])  # fmt: skip
    variants = variants_of(run, list(range(AGENTS)))
    assert compiled_agents(run, variants) == set(range(AGENTS))
    made = Engine(run, variants, backend=compiled_backend).backend
    assert isinstance(made, CompiledBackend)
    return made


def _draw(rng: np.random.Generator, rows: int):
    agents = sorted(rng.choice(AGENTS, size=rows, replace=False).tolist())
    counts = torch.from_numpy(rng.integers(1, 9, size=rows))
    horizons = torch.from_numpy(rng.choice([3, 40, 200, 500, 900], size=rows))
    theta = torch.from_numpy(rng.normal(0, 0.5, size=(rows, PARAMS)).astype(np.float32))
    seed, round_index, iteration = (int(rng.integers(0, top)) for top in (2**40, 10**6, 5))
    draws = Draws(seed, torch.tensor(agents), round_index, Purpose.TRAIN, iteration)
    return theta, counts, draws, horizons, agents


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("greedy", [False, True])
def test_a_keyed_sample_is_the_keys_then_the_sample(backend, seed: int, greedy: bool) -> None:
    rng = np.random.default_rng(seed)
    theta, counts, draws, horizons, agents = _draw(rng, int(rng.integers(1, AGENTS + 1)))
    batch = backend.sample(theta, counts, draws, horizons, agents, greedy=greedy)
    count = counts.numpy()
    limits = np.minimum(horizons.numpy(), CARTPOLE_STEP_LIMIT)
    capacity = int(count @ limits)
    obs = np.zeros((capacity, 4), np.float32)
    action, column, time = (np.zeros(capacity, np.int64) for _ in range(3))
    lengths = np.zeros(int(count.sum()), np.int64)
    written = kernels.sample_rows(
        theta.numpy(), backend.sizes, backend._physics_rows(agents), count, limits,
        backend.keys(draws, counts).numpy(), greedy, obs, action, column, time, lengths,
    )  # fmt: skip
    steps = batch.steps
    assert steps is not None and len(steps.obs) == written
    assert np.array_equal(steps.obs.numpy(), obs[:written])
    assert np.array_equal(steps.actions.numpy(), action[:written])
    assert np.array_equal(steps.column.numpy(), column[:written])
    assert np.array_equal(steps.time.numpy(), time[:written])
    assert np.array_equal(batch.lengths().numpy(), lengths)
    assert torch.equal(batch.owner, torch.repeat_interleave(torch.arange(len(agents)), counts))
    starts = np.concatenate([[0], np.cumsum(lengths)[np.cumsum(count) - 1]])
    assert np.array_equal(steps.row_start.numpy(), starts)
    assert torch.equal(batch.steps_per_row(), torch.from_numpy(np.diff(starts)))


def _weights(rng: np.random.Generator, batch: Trajectories, kind: str) -> torch.Tensor | None:
    if kind == "none":
        return None
    columns = int(batch.owner.shape[0])
    shape = (columns,) if kind == "trajectory" else (batch.longest + 3, columns)
    return torch.from_numpy(rng.uniform(0.2, 2.0, size=shape))


@pytest.mark.parametrize("seed", range(4))
def test_the_fused_mean_gradients_are_their_definition_to_the_bit(backend, seed: int) -> None:
    rng = np.random.default_rng(seed)
    compared = 0
    for options, weighting in itertools.product(OPTIONS, ("none", "trajectory", "decision")):
        if weighting == "decision" and options.estimator == "reinforce":
            continue  # refused by the definition (test_compiled_estimator.py)
        theta, counts, draws, horizons, agents = _draw(rng, int(rng.integers(1, AGENTS + 1)))
        gammas = torch.from_numpy(rng.choice([0.9, 0.97, 0.99, 1.0], size=len(agents)))
        batch = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
        weights = _weights(rng, batch, weighting)
        ours = backend.mean_gradients(theta, batch, options, gammas, weights)
        expected = defined_mean_gradients(backend, theta, batch, options, gammas, weights)
        assert torch.equal(ours, expected), (options, weighting)
        compared += int(options.normalize == "none" and bool(ours.abs().sum() > 0))
    assert compared >= 12, "too few of the 16 fused cases had a gradient to compare"


def test_renamed_rows_take_the_fused_path_to_the_same_bits(backend) -> None:
    """A batch whose rows were renamed (rows that sample nothing between them) gives each row
    its own θ and γ."""
    rng = np.random.default_rng(7)
    theta, counts, draws, horizons, agents = _draw(rng, 3)
    batch = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
    positions = torch.tensor([1, 3, 4])
    renamed = batch.regrouped(positions, 6)
    wide = torch.from_numpy(rng.normal(0, 0.5, size=(6, PARAMS)).astype(np.float32))
    wide[positions] = theta
    gammas = torch.tensor([0.5, 0.9, 0.6, 0.97, 0.99, 0.7], dtype=torch.float64)
    options = EstimatorOptions()
    ours = backend.mean_gradients(wide, renamed, options, gammas, None)
    assert renamed.native is batch.native
    expected = defined_mean_gradients(backend, wide, renamed, options, gammas, None)
    assert torch.equal(ours, expected)
    assert torch.equal(ours[positions], backend.mean_gradients(
        theta, batch, options, gammas[positions], None))  # fmt: skip
    assert not bool(ours[[0, 2, 5]].any()) and bool(ours[positions].any())


def test_a_held_batch_keeps_its_steps_while_another_is_sampled(backend) -> None:
    """A batch's packed steps are made when first read, from the sampler's reused arrays: a
    batch still held when the next is sampled keeps its own."""
    rng = np.random.default_rng(11)
    theta, counts, draws, horizons, agents = _draw(rng, 4)
    first = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
    again = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
    assert again.steps is not None
    kept = again.steps.obs.clone()
    other = draws._replace(iteration=draws.iteration + 1)
    second = backend.sample(theta, counts, other, horizons, agents, greedy=False)
    assert first.steps is not None and second.steps is not None
    assert torch.equal(first.steps.obs, kept)
    assert not torch.equal(second.steps.obs[: len(kept)], kept[: len(second.steps.obs)])


@pytest.mark.parametrize(
    "algo", [["algo=fedhpg"], ["algo=fedhpgvr"], ["algo=fedpgbr", "strategy=fedpgbr"]]
)
def test_a_round_is_the_composed_rounds_to_the_bit(monkeypatch, algo: list[str]) -> None:
    """A whole round of each algorithm (agents of different τ_k: rows whose τ_k is spent
    sample nothing) is the round the composed primitives give."""
    run = resolve_config(overrides=[
        "env=cartpole", "agents=population", "policy.hidden=[16,16]", "agents.num_agents=5",
        *algo,
    ])  # fmt: skip
    agents = list(range(5))

    def trained() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        group = make_agent_group(run, agents)
        theta = torch.linspace(-0.3, 0.3, group.num_params)
        result = group.train(3, theta, agents).result
        stats = result.stats
        return result.thetas, np.asarray(stats.env_steps), np.asarray(stats.trajectories)

    fused = trained()
    monkeypatch.setattr(CompiledBackend, "mean_gradients", defined_mean_gradients)
    composed = trained()
    for ours, expected in zip(fused, composed, strict=True):
        assert np.array_equal(ours, expected)
    assert fused[1].sum() > 0
    if algo == ["algo=fedhpg"]:  # budgets differ, so some rows sit out a later iteration
        assert len(set(fused[2].tolist())) > 1


@pytest.mark.parametrize("chunk_steps", [1, 60, 8192])
@pytest.mark.parametrize("seed", range(3))
def test_drawn_with_their_gradients_a_chunk_at_a_time_is_the_whole_batch_to_the_bit(
    backend, chunk_steps: int, seed: int
) -> None:
    """The sample drawn a few rows at a time with its gradients (a chunk of 1 step: every
    row alone) writes the lengths, rows and row starts the whole sample writes and gives the
    gradients the drawn batch gives, at a θ other than the one it was drawn at; its sampling
    time is counted."""
    rng = np.random.default_rng(100 + seed)
    rows = int(rng.integers(2, AGENTS + 1))
    theta, counts, draws, horizons, agents = _draw(rng, rows)
    at = theta + torch.from_numpy(rng.normal(0, 0.1, size=theta.shape).astype(np.float32))
    gammas = torch.from_numpy(rng.choice([0.9, 0.97, 0.99, 1.0], size=rows))
    for options in (EstimatorOptions(), EstimatorOptions(estimator="reinforce", baseline="none")):
        whole = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
        assert whole.steps is not None  # drawn whole first
        expected = backend.mean_gradients(at, whole, options, gammas, None)
        draw = backend.sample(theta, counts, draws, horizons, agents, greedy=False).native
        kernel = backend._unweighted
        assert kernel is not None and kernel[0] is options
        out = np.zeros(tuple(at.shape), dtype=np.float32)
        capacity = fused.chunk_capacity(draw.count, draw.limits, chunk_steps)
        types = (kernels.ACTION, kernels.COLUMN, kernels.TIME)
        drawn, seconds = fused.sampled_gradients(
            *draw.words, draw.thetas, at.numpy(), backend.sizes, draw.physics, draw.count,
            draw.limits, False, kernel[1].gpomdp, kernel[1].mean_baseline, kernel[1].from_step,
            kernel[1].weights, gammas.numpy(), chunk_steps, np.ones(capacity),
            np.empty((capacity, 4), np.float32), *(np.empty(capacity, t) for t in types),
            draw.lengths, draw.owner, draw.row_start, out,
        )  # fmt: skip
        assert np.array_equal(out, expected.numpy()), options
        assert bool(out.any())
        assert drawn == len(whole.steps.obs) and seconds > 0
        assert np.array_equal(draw.lengths, whole.lengths().numpy())
        assert np.array_equal(draw.owner, whole.owner.numpy())
        assert np.array_equal(draw.row_start, whole.steps.row_start.numpy())


def test_a_batch_drawn_with_its_gradients_is_drawn_whole_when_its_steps_are_read(backend) -> None:
    """mean_gradients draws a batch with its gradients; reading its steps afterwards draws it
    whole, the same trajectories; the batch reports the CPU time of both as sampling."""
    rng = np.random.default_rng(5)
    theta, counts, draws, horizons, agents = _draw(rng, 4)
    gammas = torch.full((4,), 0.99, dtype=torch.float64)
    batch = backend.sample(theta, counts, draws, horizons, agents, greedy=False)
    assert batch.late_sampling_s() == 0.0 and batch.native.whole is None
    first = backend.mean_gradients(theta, batch, EstimatorOptions(), gammas, None)
    assert batch.native.whole is None and batch.late_sampling_s() > 0
    lengths = batch.lengths().clone()
    drawn = batch.late_sampling_s()
    assert batch.steps is not None and batch.native.whole is not None
    assert batch.late_sampling_s() > drawn
    assert torch.equal(batch.lengths(), lengths)
    assert torch.equal(
        backend.mean_gradients(theta, batch, EstimatorOptions(), gammas, None), first
    )
