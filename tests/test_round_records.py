"""A round's record (metrics line, TensorBoard, checkpoint) is written while the next round's
agents train, and never lost: written before the run returns or raises, in round order, once."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import pytest
import torch

from fedhpg.common.heterogeneity.variants import variant_of
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.runtime.cli import compose
from fedhpg.server.coordinator import Coordinator, RoundRecord
from fedhpg.server.pools import FederationError, RoundAnswers
from fedhpg.server.pools.inprocess import make_in_process_pool
from fedhpg.server.strategies import make_strategy

RUN = ["env=gridworld", "rounds=4", "eval.every=2", "eval.episodes=2"]


class RemoteLikePool:
    """A real in-process pool that calls ``while_training`` as the zmq pool does: after its
    requests are out (logged), before the agents' answers; and fails round ``fail_in`` before
    any request goes out, as a pool that lost every agent does."""

    def __init__(self, run: Any, log: list[str], fail_in: int | None = None) -> None:
        self.inner = make_in_process_pool(run)
        self.log = log
        self.fail_in = fail_in

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        while_training: Callable[[], None] | None = None,
        private: RoundPrivacy | None = None,
    ) -> RoundAnswers:
        if round_index == self.fail_in:
            raise FederationError(f"round {round_index}: every agent is gone")
        self.log.append(f"requests {round_index}")
        if while_training is not None:
            while_training()
        answers = self.inner.train(round_index, theta, agents, budgets=budgets, private=private)
        self.log.append(f"answers {round_index}")
        return answers


def _coordinator(pool: RemoteLikePool, log: list[str]) -> Coordinator:
    run = compose(RUN)

    def write(record: RoundRecord, theta: torch.Tensor) -> None:
        log.append(f"record {record.round}")

    return Coordinator(
        run=run,
        pool=pool,  # type: ignore[arg-type]
        strategy=make_strategy(run.strategy, run=run),
        theta=initial_theta(variant_of(run, 0), run),
        on_round=[write],
    )


def test_a_rounds_record_is_written_while_the_next_round_trains() -> None:
    log: list[str] = []
    pool = RemoteLikePool(compose(RUN), log)
    try:
        _coordinator(pool, log).run_rounds()
    finally:
        pool.inner.close()
    assert log == [
        "requests 1", "answers 1",
        "requests 2", "record 1", "answers 2",
        "requests 3", "record 2", "answers 3",
        "requests 4", "record 3", "answers 4",
        "record 4",  # the last round's, before run_rounds returns
    ]  # fmt: skip


def test_a_failed_round_still_writes_the_round_before() -> None:
    log: list[str] = []
    pool = RemoteLikePool(compose(RUN), log, fail_in=3)
    try:
        with pytest.raises(FederationError, match="round 3"):
            _coordinator(pool, log).run_rounds()
    finally:
        pool.inner.close()
    assert log == ["requests 1", "answers 1", "requests 2", "record 1", "answers 2", "record 2"]


def test_a_record_that_cannot_be_written_stops_the_run_and_is_not_retried() -> None:
    log: list[str] = []
    pool = RemoteLikePool(compose(RUN), log)
    coordinator = _coordinator(pool, log)
    calls: list[int] = []

    def disk_full(record: RoundRecord, theta: torch.Tensor) -> None:
        calls.append(record.round)
        if record.round == 2:
            raise OSError("no space left on device")

    coordinator.on_round.append(disk_full)
    try:
        with pytest.raises(OSError, match="no space"):
            coordinator.run_rounds()
    finally:
        pool.inner.close()
    assert calls == [1, 2], "round 2's record was tried once, and no round after it trained on"
    assert "answers 3" not in log


def test_bench_scale_times_a_round_from_one_theta_to_the_next_less_evaluations() -> None:
    from benchmarks.scale import round_walls

    records = [
        {"wall_time_s": 0.50, "round_time_s": 0.40},
        {"wall_time_s": 0.62, "round_time_s": 0.10},  # 20 ms between the rounds counted
        {"wall_time_s": 0.95, "round_time_s": 0.11, "eval_time_s": 0.20},
    ]
    round_walls(records)
    walls = [r["round_wall_s"] for r in records]
    assert walls == pytest.approx([0.40, 0.12, 0.13])
