"""What the engine does off the CPU for determinism, exercised on the CPU.

A GPU may pick a kernel, and so its rounding, by a call's shape, and adds a scatter's values
with atomics: off the CPU the sampler's policy calls take a fixed number of tiles
(``Engine.act_tiles_per_call``) and the engine runs under torch's deterministic algorithms
(``deterministic_off_cpu``). Neither shows a GPU's rounding here; these tests check that the
fixed-shape calls, forced on, give the CPU's θ bit for bit in any company, and that the
deterministic setting is the caller's again afterwards.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.engine.devices import deterministic_off_cpu
from fedhpg.common.learning.engine.memory import packed_elements
from fedhpg.common.learning.engine.sampling import ACT_TILE, act_tiles_per_call
from fedhpg.common.learning.group import EngineGroup
from fedhpg.common.learning.policies import Params
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.tensor_writes import put_distinct

FAMILIES = {
    "pendulum": ["env=pendulum", "policy.hidden=[16,16]", "env.horizon=40"],
    "gridworld": ["env=gridworld"],
}


def _recorded(act: Callable[..., torch.Tensor], calls: list[int]) -> Callable[..., torch.Tensor]:
    """A policy's ``act_with`` that records each call's tiles in ``calls``."""

    def recorded(params: Params, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        calls.append(obs.shape[0])
        return act(params, obs, noise)

    return recorded


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_fixed_shape_policy_calls_give_the_same_theta_in_any_company(
    family: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = compose([*FAMILIES[family], "agents=population", "agents.num_agents=9",
                   "algo.engine=torch", "algo.device=cpu"])  # fmt: skip
    theta = initial_theta(variants_of(run, [0])[0], run)
    plain = EngineGroup(run, variants_of(run, [4])).train(3, theta, [4]).result.theta_of(4)
    calls: list[int] = []
    for company in ([4], list(range(9)), [8, 4, 1]):
        group = EngineGroup(run, variants_of(run, company))
        group.engine.backend.act_tiles_per_call = 3  # what a GPU gets, forced on
        policy = group.engine.backend.policy.policy  # the sampler calls its act_with
        monkeypatch.setattr(policy, "act_with", _recorded(policy.act_with, calls))
        assert np.array_equal(group.train(3, theta, company).result.theta_of(4), plain)
    assert calls and set(calls) == {3}, "every policy call takes exactly 3 tiles"


CUDA = torch.device("cuda")  # only its type is read: no CUDA device is needed


def test_a_gpus_policy_calls_are_sized_by_the_run_and_split_evenly() -> None:
    mlp = 386  # CartPole's 16-16 MLP
    largest = packed_elements(CUDA) // (ACT_TILE * mlp)
    assert largest == 21_732
    assert act_tiles_per_call(torch.device("cpu"), mlp, 1000) is None  # one call a step
    assert act_tiles_per_call(CUDA, mlp, 1) == 1
    assert act_tiles_per_call(CUDA, mlp, 1000) == 1000  # not padded to 21,732 tiles
    assert act_tiles_per_call(CUDA, mlp, largest) == largest
    assert act_tiles_per_call(CUDA, mlp, largest + 1) == (largest + 2) // 2  # two even calls
    assert act_tiles_per_call(CUDA, mlp, 65_536) == 16_384  # four calls, none mostly empty
    assert act_tiles_per_call(CUDA, 10**9, 10) == 1  # a policy too large for one tile a call


def _setting() -> tuple[bool, bool]:
    return (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
    )


def test_deterministic_algorithms_off_the_cpu_and_the_callers_setting_back() -> None:
    before = _setting()
    assert before == (False, False)
    with deterministic_off_cpu(CUDA):
        assert _setting() == (True, True)
    assert _setting() == before
    with pytest.raises(RuntimeError), deterministic_off_cpu(CUDA):
        raise RuntimeError("a failure inside")
    assert _setting() == before
    with deterministic_off_cpu(torch.device("cpu")):
        assert _setting() == before  # the CPU is left alone


@pytest.mark.parametrize("warn_only", [False, True])
def test_a_callers_own_deterministic_setting_is_kept(warn_only: bool) -> None:
    before = _setting()
    torch.use_deterministic_algorithms(True, warn_only=warn_only)
    try:
        with deterministic_off_cpu(CUDA):
            assert _setting() == (True, warn_only)
        assert _setting() == (True, warn_only)
    finally:
        torch.use_deterministic_algorithms(*before[:1], warn_only=before[1])


def test_a_write_to_distinct_positions_keeps_the_deterministic_setting() -> None:
    """``put_distinct`` leaves deterministic mode for its one write (off the CPU, where the mode
    would sort the indices) and puts the caller's setting back: exercised on torch's meta
    device, which is not the CPU."""
    before = _setting()
    for warn_only in (False, True):
        torch.use_deterministic_algorithms(True, warn_only=warn_only)
        try:
            target = torch.zeros(6, 3, device="meta")
            put_distinct(
                target, (torch.tensor([4, 1], device="meta"),), torch.ones(2, 3, device="meta")
            )
            assert _setting() == (True, warn_only)
        finally:
            torch.use_deterministic_algorithms(*before[:1], warn_only=before[1])
    cpu = torch.zeros(5)
    put_distinct(cpu, torch.tensor([3, 0]), torch.tensor([2.0, 7.0]))
    assert cpu.tolist() == [7.0, 0.0, 0.0, 2.0, 0.0]
    assert _setting() == before
