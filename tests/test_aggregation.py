"""Aggregation (Algorithm 1 line 9): means in agent order, arrival order irrelevant."""

from __future__ import annotations

import itertools

import pytest
import torch

from fedhpg.common.aggregation import AgentResult, aggregate


def _results() -> list[AgentResult]:
    generator = torch.Generator().manual_seed(0)
    return [
        AgentResult(agent_index=k, theta=torch.randn(1000, generator=generator), trajectories=t)
        for k, t in enumerate([10, 20, 30, 40])
    ]


def test_uniform_mean() -> None:
    results = _results()
    expected = torch.stack([r.theta for r in results]).mean(0)
    torch.testing.assert_close(aggregate(results), expected)


def test_weighted_mean_by_trajectories() -> None:
    results = _results()
    weights = torch.tensor([0.1, 0.2, 0.3, 0.4])
    expected = (weights[:, None] * torch.stack([r.theta for r in results])).sum(0)
    torch.testing.assert_close(aggregate(results, rule="weighted"), expected)


@pytest.mark.parametrize("rule", ["uniform", "weighted"])
def test_arrival_order_cannot_change_a_bit(rule: str) -> None:
    results = _results()
    reference = aggregate(results, rule=rule)
    for order in itertools.permutations(results):
        assert torch.equal(aggregate(list(order), rule=rule), reference)


def test_errors_are_named() -> None:
    with pytest.raises(ValueError, match="zero agent results"):
        aggregate([])
    with pytest.raises(ValueError, match="'median'"):
        aggregate(_results(), rule="median")
