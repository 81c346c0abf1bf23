"""One round result from the engine to the strategy (common/records/types.py ``RoundResult``).

Parts of a round concatenate into agent order with every row's θ and statistics kept (map
columns None where a part has no such key); a SplitGroup's round moves each iteration's
positions to its agents' rows; the wire carries the result as it is.
"""

from __future__ import annotations

import numpy as np
import pytest

from fedhpg.common.records.round_columns import IterationColumns, TrainedRound
from fedhpg.common.records.types import RoundResult, UpdateColumns, UpdateStats
from fedhpg.common.wire.codec import decode, encode


def _result(agents: list[int], algorithm: dict[str, float] | None = None) -> RoundResult:
    stats = [
        UpdateStats(
            trajectories=k + 1,
            env_steps=10 * (k + 1),
            compute_s=0.5 * k,
            train_return=float(k),
            algorithm=dict(algorithm or {}),
        )
        for k in agents
    ]
    thetas = np.array([[k, -k, 0.5 * k] for k in agents], dtype=np.float32).reshape(-1, 3)
    return RoundResult(round=4, agents=agents, thetas=thetas, stats=UpdateColumns.of(stats))


def test_parts_concatenate_into_agent_order_row_by_row() -> None:
    first, second = _result([5, 1], {"iw_mean": 1.5}), _result([3, 0, 9])
    whole = RoundResult.concatenated([first, second])
    assert whole.agents == [0, 1, 3, 5, 9] and whole.round == 4
    for k in (0, 1, 3, 5, 9):
        part = first if k in first.agents else second
        assert np.array_equal(whole.theta_of(k), part.theta_of(k))
        assert whole.stats_of(k) == part.stats_of(k)
    assert whole.stats.algorithm == {"iw_mean": [None, 1.5, None, 1.5, None]}


def test_slices_gathered_rows_and_an_empty_result() -> None:
    result = _result([0, 2, 4, 6])
    head = result[:2]
    assert head.agents == [0, 2] and np.shares_memory(head.thetas, result.thetas)
    taken = result.taking([3, 1])
    assert taken.agents == [6, 2] and np.array_equal(taken.thetas, result.thetas[[3, 1]])
    assert result.taking([0, 1, 2, 3]) is result
    rows = UpdateColumns.gathered([(result.stats, 3), (head.stats, 0)])
    assert list(rows) == [result.stats_of(6), result.stats_of(0)]
    empty = RoundResult.empty(4, 3)
    assert len(empty) == 0 and empty.thetas.shape == (0, 3) and list(empty.stats) == []
    with pytest.raises(TypeError, match="cut by slices"):
        result[0]  # an agent is read with theta_of / stats_of
    with pytest.raises(ValueError):
        result.theta_of(1)


def test_split_rounds_move_their_iterations_to_the_agents_rows() -> None:
    def iteration(positions: list[int], steps: list[int]) -> IterationColumns:
        count = len(positions)
        return IterationColumns(
            positions=np.array(positions, dtype=np.int64),
            compute_s=np.zeros(count),
            env_steps=np.array(steps, dtype=np.int64),
            grad_steps=np.zeros(count, dtype=np.int64),
        )

    honest = TrainedRound(_result([0, 4]), [iteration([0, 1], [7, 9]), iteration([1], [11])])
    attackers = TrainedRound(_result([2]), [iteration([0], [5])])
    whole = TrainedRound.concatenated([honest, attackers])
    assert whole.result.agents == [0, 2, 4]
    steps = sorted(
        (whole.result.agents[p], s)
        for ran in whole.iterations
        for p, s in zip(ran.positions.tolist(), ran.env_steps.tolist(), strict=True)
    )
    assert steps == [(0, 7), (2, 5), (4, 9), (4, 11)]


def test_the_wire_carries_the_result_itself() -> None:
    result = _result([1, 2, 3], {"iw_max": 2.0})
    received = decode(encode(result))
    assert type(received) is RoundResult
    assert received.agents == result.agents and received.round == result.round
    assert np.array_equal(received.thetas, result.thetas)
    assert list(received.stats) == list(result.stats)
