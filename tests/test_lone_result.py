"""A lone agent's round result, built without the columns' records, is the record the columns
give (every field, the algorithm's statistics with and without values)."""

from __future__ import annotations

import pytest
import torch

from fedhpg.common.group import make_agent_group
from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import initial_theta


@pytest.mark.parametrize(
    "overrides",
    [
        ["algo=fedhpgvr"],  # importance-weight statistics
        ["algo=fedhpg", "algo.bound_estimates=true", "algo.grad_clip=0.01"],  # None where τ = 1
    ],
)
def test_the_lone_result_is_the_columns_record(overrides: list[str]) -> None:
    run = compose(["env=cartpole", "policy.hidden=[8]", "agents=population", "agents.num_agents=1",
                   *overrides])  # fmt: skip
    group = make_agent_group(run, [0])
    theta = initial_theta(variants_of(run, [0])[0], run)
    columns = group.train_columns(3, theta, [0])  # type: ignore[attr-defined]
    lone, general = columns.lone_result(), columns.result(0)
    assert lone.stats == general.stats
    assert lone.stats.algorithm  # the algorithm's statistics came through
    assert torch.equal(lone.theta, general.theta)
