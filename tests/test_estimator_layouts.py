"""The estimator on two layouts of one batch: each trajectory extended to its agent's longest
(the dead cells a per-step baseline reaches) or stopped at its own last step. Without a
per-step baseline the coefficients of the steps that happened are the same bits on both;
GPOMDP's per-step baseline reaches the dead cells, and the stopped layout is refused there."""

from __future__ import annotations

import itertools

import pytest
import torch

from fedhpg.common.learning import estimators
from fedhpg.common.learning.staircase import Staircase

OPTIONS = [
    (estimator, baseline, to_go, normalize)
    for estimator, baseline, to_go, normalize in itertools.product(
        ("reinforce", "gpomdp"), ("none", "mean"), ("from_start", "from_step"), ("none", "episode")
    )
    if not (estimator == "reinforce" and to_go == "from_step")
    and not (estimator == "gpomdp" and baseline == "mean")
]


def _batch(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ragged groups (one of a single trajectory), lengths 1-60, rewards of both signs and
    scales, one γ per group."""
    generator = torch.Generator().manual_seed(seed)
    sizes = torch.tensor([4, 1, 7, 2, 3, 5, 6])
    groups = torch.repeat_interleave(torch.arange(len(sizes)), sizes)
    lengths = torch.randint(1, 60, (len(groups),), generator=generator)
    rewards = torch.randn(int(lengths.sum()), generator=generator, dtype=torch.float64)
    rewards *= torch.exp(3 * torch.rand(rewards.shape, generator=generator, dtype=torch.float64))
    gammas = 0.9 + 0.1 * torch.rand(len(sizes), generator=generator, dtype=torch.float64)
    return groups, lengths, rewards, gammas[groups]


def _on(
    layout: Staircase, lengths: torch.Tensor, rewards: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The steps' rewards (each trajectory's in time order, trajectory after trajectory) on
    the cells of ``layout``, 0 elsewhere; and the cell of each step."""
    column = torch.repeat_interleave(torch.arange(len(lengths)), lengths)
    time = torch.arange(len(column)) - (torch.cumsum(lengths, 0) - lengths)[column]
    cells = layout.cell(time, column)
    return torch.zeros(layout.size, dtype=torch.float64).index_copy_(0, cells, rewards), cells


@pytest.mark.parametrize(("estimator", "baseline", "to_go", "normalize"), OPTIONS)
def test_stopping_each_trajectory_at_its_end_changes_no_bit(
    estimator: str, baseline: str, to_go: str, normalize: str
) -> None:
    for seed in range(3):
        groups, lengths, rewards, gamma = _batch(seed)
        grouped = Staircase.of_groups(lengths, groups)
        own = Staircase(lengths)
        assert own.size == int(lengths.sum()) < grouped.size  # the check has dead cells to skip
        results = []
        for layout in (grouped, own):
            cell_rewards, cells = _on(layout, lengths, rewards)
            alive = torch.zeros(layout.size, dtype=torch.bool).index_fill_(0, cells, True)
            coefficients = estimators.coefficients(
                estimator, layout, cell_rewards, None if layout is own else alive,  # type: ignore[arg-type]
                gamma=gamma, baseline=baseline, reward_to_go=to_go,  # type: ignore[arg-type]
                normalize=normalize, groups=groups,  # type: ignore[arg-type]
            )  # fmt: skip
            results.append(coefficients.index_select(0, cells))
        expected, got = results
        assert torch.equal(got, expected), (seed, (got - expected).abs().max())
        assert bool(expected.ne(0).any())


@pytest.mark.parametrize("weighted", [False, True])
def test_a_per_step_baseline_on_stopped_trajectories_is_refused(weighted: bool) -> None:
    """GPOMDP's per-step baseline has a term at every dead step up to the agent's longest: a
    layout that stops each trajectory at its end would drop them, and is refused."""
    groups, lengths, rewards, gamma = _batch(1)
    own = Staircase(lengths)
    weights = torch.ones(len(groups), dtype=torch.float64) if weighted else None
    with pytest.raises(ValueError, match="group's longest"):
        estimators.coefficients(
            "gpomdp", own, _on(own, lengths, rewards)[0], None, gamma=gamma,
            baseline="mean", weights=weights, groups=groups,
        )  # fmt: skip
