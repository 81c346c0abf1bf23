"""The estimator's per-group sums without atomics: what a GPU runs gives the CPU's bits.

A GPU's ``index_add_`` adds float64 with atomics in whatever order its threads arrive, so the
estimator's baselines, normalisations and per-row statistics would change from run to run
there, and θ with them. :func:`fedhpg.common.learning.staircase.ordered_sums` adds each group's
entries in index order without atomics off the CPU. Here that formulation runs on the CPU: bit for
bit ``index_add_``'s sums, alone and inside every estimator option; a sum in another order
(reversed) does not match, so the check can tell. On a machine with CUDA the same holds on the
device (skipped elsewhere).
"""

from __future__ import annotations

import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning import estimators, importance, staircase
from fedhpg.common.learning.engine import torch_backend, trajectories
from fedhpg.common.learning.group import EngineGroup
from fedhpg.common.learning.staircase import Staircase, _summed_by_columns, ordered_sums
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose


def _values(count: int, *shape: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    scale = torch.exp(8 * torch.rand(count, *shape, generator=generator, dtype=torch.float64))
    return torch.randn(count, *shape, generator=generator, dtype=torch.float64) * scale


def _index(count: int, size: int, seed: int = 1) -> torch.Tensor:
    return torch.randint(0, size - 1, (count,), generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("shape", [(), (3,), (2, 5)])
def test_sums_by_columns_are_index_adds_bits(shape: tuple[int, ...]) -> None:
    values, index = _values(4000, *shape), _index(4000, 37)  # group 36 stays empty
    values[::97] = -0.0
    expected = values.new_zeros((37, *shape)).index_add_(0, index, values)
    got = _summed_by_columns(index, values, values.new_zeros((37, *shape)))
    assert torch.equal(got, expected) and torch.equal(got.signbit(), expected.signbit())
    assert torch.equal(ordered_sums(index, values, 37), expected)
    assert torch.equal(
        _summed_by_columns(index[:0], values[:0], values.new_zeros(4)), values.new_zeros(4)
    )


def test_a_sorted_index_is_summed_without_a_sort(monkeypatch: pytest.MonkeyPatch) -> None:
    values, index = _values(4000, 3), _index(4000, 37).sort().values  # a staircase's order
    expected = values.new_zeros((37, 3)).index_add_(0, index, values)

    def refused(*args: object, **kwargs: object) -> torch.Tensor:
        raise AssertionError("sorted an index that was sorted already")

    monkeypatch.setattr(torch, "argsort", refused)
    assert torch.equal(_summed_by_columns(index, values, values.new_zeros((37, 3))), expected)


def test_a_sum_in_another_order_differs_in_its_bits() -> None:
    values, index = _values(4000), _index(4000, 37)
    expected = values.new_zeros(37).index_add_(0, index, values)
    flipped = _summed_by_columns(index.flip(0), values.flip(0), values.new_zeros(37))
    assert not torch.equal(flipped, expected), "the check could not tell a reordered sum"


def _columns_everywhere(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ordered sum the maths imports takes the GPU's formulation, on the CPU."""

    def by_columns(index: torch.Tensor, values: torch.Tensor, size: int) -> torch.Tensor:
        return _summed_by_columns(index, values, values.new_zeros((size, *values.shape[1:])))

    for module in (estimators, importance, staircase, trajectories, torch_backend):
        monkeypatch.setattr(module, "ordered_sums", by_columns)


OPTIONS = [
    ("reinforce", "mean", "from_start", "none"),
    ("gpomdp", "mean", "from_start", "none"),
    ("gpomdp", "mean", "from_step", "batch"),
    ("gpomdp", "none", "from_start", "episode"),
    ("reinforce", "mean", "from_start", "batch"),
]


@pytest.mark.parametrize(("estimator", "baseline", "to_go", "normalize"), OPTIONS)
def test_every_estimator_option_gives_the_cpus_bits_without_atomics(
    monkeypatch: pytest.MonkeyPatch, estimator: str, baseline: str, to_go: str, normalize: str
) -> None:
    generator = torch.Generator().manual_seed(3)
    groups = torch.repeat_interleave(torch.arange(7), torch.tensor([3, 1, 6, 2, 5, 4, 2]))
    lengths = torch.randint(1, 40, (len(groups),), generator=generator)
    layout = Staircase.of_groups(lengths, groups)
    alive = layout.time < lengths.index_select(0, layout.column)
    rewards = torch.randn(layout.size, generator=generator, dtype=torch.float64) * alive
    gamma = 0.9 + 0.09 * torch.rand(len(groups), generator=generator, dtype=torch.float64)

    def coefficients() -> torch.Tensor:
        return estimators.coefficients(
            estimator, layout, rewards, alive, gamma=gamma, baseline=baseline,  # type: ignore[arg-type]
            reward_to_go=to_go, normalize=normalize, groups=groups,  # type: ignore[arg-type]
        )  # fmt: skip

    weights = torch.exp(0.3 * torch.randn(len(groups), 4, generator=generator, dtype=torch.float64))
    expected = coefficients(), importance.self_normalise(weights.T, groups)
    _columns_everywhere(monkeypatch)
    got = coefficients(), importance.self_normalise(weights.T, groups)
    assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1])


def test_the_engines_gradients_give_the_cpus_bits_without_atomics(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The torch engine's per-agent sums of its tiles' gradients, too."""
    run = compose(["env=cartpole", "agents=population", "agents.num_agents=5",
                   "algo.engine=torch", "policy.hidden=[16,16]"])  # fmt: skip
    agents = list(range(5))
    theta = initial_theta(variants_of(run, [0])[0], run)

    def thetas() -> list[torch.Tensor]:
        trained = EngineGroup(run, variants_of(run, agents)).train(1, theta, agents)
        return [torch.from_numpy(trained.result.theta_of(k)) for k in agents]

    expected = thetas()
    _columns_everywhere(monkeypatch)
    assert all(torch.equal(a, b) for a, b in zip(thetas(), expected, strict=True))
    assert not all(torch.equal(a, theta) for a in expected), "the agents moved"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_on_cuda_the_sums_are_the_cpus_run_after_run() -> None:
    values, index = _values(100_000, 3), _index(100_000, 1000)
    expected = values.new_zeros((1000, 3)).index_add_(0, index, values)
    runs = [ordered_sums(index.cuda(), values.cuda(), 1000).cpu() for _ in range(3)]
    assert all(torch.equal(run, expected) for run in runs)
