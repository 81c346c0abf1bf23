"""The engine's sampler: masking after episode end, counting, horizons, returns, one policy
call per time step for every agent's copies, and trajectories that depend on their keys."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from engine_mdp import mdp_engine

from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.engine.sampling import ACT_TILE, END_CHECK
from fedhpg.common.learning.randomness import Purpose
from fedhpg.envs.base import BatchStep


class CountdownEnv:
    """Copy b ends after b + 1 steps with reward 1 per step; afterwards it keeps emitting
    reward 100 so that any leak of post-episode steps into returns is visible."""

    def __init__(self, num_envs: int, *, truncate: bool = False) -> None:
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(4)
        self.single_action_space = gym.spaces.Discrete(2)
        self.truncate = truncate
        self.t = 0

    def reset(self, *, seed: int) -> np.ndarray:
        self.t = 0
        return np.zeros(self.num_envs, dtype=np.int64)

    def step(self, actions: np.ndarray) -> BatchStep:
        self.t += 1
        ends = np.arange(self.num_envs) + 1
        finished = self.t == ends
        after = self.t > ends
        return BatchStep(
            obs=np.full(self.num_envs, min(self.t, 3), dtype=np.int64),
            reward=np.where(after, 100.0, 1.0),
            terminated=finished & (not self.truncate),
            truncated=finished & self.truncate,
            success=finished,
        )

    def close(self) -> None:
        pass


def _countdown(rows: int = 1, truncate: bool = False, horizon: int = 10) -> Engine:
    return mdp_engine(lambda n: CountdownEnv(n, truncate=truncate), horizon, rows, gamma=1.0)


def _sample(engine: Engine, counts: list[int], **keywords: object):
    rows = engine.begin(1, torch.zeros(8), list(range(len(counts))))
    return rows.sample(rows.theta, torch.tensor(counts), iteration=0, **keywords)


@pytest.mark.parametrize("truncate", [False, True])
def test_steps_after_episode_end_neither_count_nor_leak(truncate: bool) -> None:
    batch = _sample(_countdown(truncate=truncate), [4])
    np.testing.assert_array_equal(batch.lengths().numpy(), [1, 2, 3, 4])
    np.testing.assert_array_equal(batch.returns().numpy(), [1.0, 2.0, 3.0, 4.0])
    assert int(batch.steps_per_row()[0]) == 10
    assert batch.obs.shape[0] == 4, "sampling stops once every copy is done"
    assert bool(batch.success.all())


def test_horizon_cuts_episodes() -> None:
    batch = _sample(_countdown(horizon=2), [4])
    np.testing.assert_array_equal(batch.lengths().numpy(), [1, 2, 2, 2])
    assert int(batch.steps_per_row()[0]) == 7
    np.testing.assert_array_equal(batch.success.numpy(), [True, True, False, False])


def test_each_row_keeps_its_own_horizon_and_discount() -> None:
    engine = _countdown(rows=2)
    rows = engine.begin(1, torch.zeros(8), [0, 1])
    batch = rows.sample(rows.theta, torch.tensor([3, 3]), iteration=0,
                          horizons=torch.tensor([2, 5]))  # fmt: skip
    np.testing.assert_array_equal(batch.lengths().numpy(), [1, 2, 2, 1, 2, 3])
    discounted = batch.returns(torch.tensor([0.5, 0.5], dtype=torch.float64))
    np.testing.assert_allclose(discounted.numpy(), [1.0, 1.5, 1.5, 1.0, 1.5, 1.75])


def test_one_policy_call_per_time_step_for_every_agent(monkeypatch: pytest.MonkeyPatch) -> None:
    engine = _countdown(rows=3)
    calls: list[tuple[int, ...]] = []
    policy = engine.backend.policy.policy  # the sampler calls its act_with on θ's parameters
    original = policy.act_with

    def counting(params, obs, noise):  # type: ignore[no-untyped-def]
        calls.append(tuple(obs.shape))
        return original(params, obs, noise)

    monkeypatch.setattr(policy, "act_with", counting)
    batch = _sample(engine, [4, 2, 3])
    longest, horizon = batch.obs.shape[0], 10
    stepped = min(horizon, -(-longest // END_CHECK) * END_CHECK)  # up to the next end check
    assert len(calls) == stepped, "one call per time step"
    assert set(calls) == {(3, ACT_TILE)}, "all three agents' copies in every call (a tile each)"


def test_the_same_keys_give_the_same_batch_and_others_another() -> None:
    engine = mdp_engine(lambda n: CountdownEnv(n), 10, 2, gamma=1.0)
    first, second = (_sample(engine, [3, 3]) for _ in range(2))
    assert torch.equal(first.actions, second.actions)
    evaluation = _sample(engine, [3, 3], purpose=Purpose.EVALUATE)
    assert not torch.equal(first.actions, evaluation.actions), "another purpose, other draws"
