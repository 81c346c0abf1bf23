"""The device-resident path end to end: every torch family's agents keep their θ in any company.

Population budgets (agents of 4, 8 and 16 trajectories side by side), so a batch's shapes
change with the company; each family's agent 4 trained alone, beside all nine and beside two
others gives the same θ and statistics, bit for bit. On the CPU here; on a CUDA device too
where there is one (the deterministic sums and fixed-shape products are what it needs).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.group import TIMING_STATS, EngineGroup
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose

FAMILIES = {
    "cartpole": ["env=cartpole", "policy.hidden=[16,16]"],
    "acrobot": ["env=acrobot", "policy.hidden=[16,16]", "env.horizon=40"],
    "pendulum": ["env=pendulum", "policy.hidden=[16,16]", "env.horizon=60"],
    "mountaincar": ["env=mountaincar", "policy.hidden=[16,16]", "env.horizon=60"],
    "gridworld": ["env=gridworld"],
}
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device on this machine"))]  # fmt: skip


def _without_times(stats):  # CPU times vary from run to run
    algorithm = {k: v for k, v in stats.algorithm.items() if k not in TIMING_STATS}
    return dataclasses.replace(stats, compute_s=0.0, algorithm=algorithm)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_an_agents_theta_on_the_device_does_not_depend_on_its_company(
    family: str, device: str
) -> None:
    run = compose([*FAMILIES[family], "agents=population", "agents.num_agents=9",
                   "algo.engine=torch", f"algo.device={device}"])  # fmt: skip
    theta = initial_theta(variants_of(run, [0])[0], run)
    trained = []
    for company in ([4], list(range(9)), [8, 4, 1]):
        group = EngineGroup(run, variants_of(run, company))
        assert group.engine.backend.family()  # type: ignore[attr-defined] is not None, "the torch family steps on the device"
        trained.append(group.train(3, theta, company).result)
    first, *others = trained
    for other in others:
        assert np.array_equal(first.theta_of(4), other.theta_of(4))
        assert _without_times(first.stats_of(4)) == _without_times(other.stats_of(4))
