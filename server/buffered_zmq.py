"""Buffered asynchronous rounds with agent processes: the order updates really arrive in.

The loop, buffer, staleness weights and bound, aggregation and records are those of
:mod:`fedhpg.server.buffered` (one implementation for both pools); only where updates come
from differs. Here each agent has its own open ``Train`` (the zmq pool's per-agent requests):
its round index is its own count of answered requests plus one, so its n-th update uses
round n's random streams and device schedule, as in process; updates join the buffer in the
order they reach the server, not in emulated-time order. With equal speeds and no sleeping a
run may still be comparable with an in-process one, but arrival order makes real-process
runs nondeterministic in general: bit-identity is the in-process virtual clock's guarantee.
With M = K every buffer holds K fresh updates from one θ̃, which is ``wait_all``.

- **Evaluation** (every ``eval.every`` versions) pauses dispatch: the aggregated agents wait,
  the others finish their updates (they queue up for the next buffers), every registered
  agent evaluates θ̃, then the waiting agents restart. No work in flight is cancelled; the
  price is the idle time of the wait.
- **Deaths:** a dead agent's update in flight is dropped; when it registers again it is sent
  the newest θ̃ under the same round index. The run goes on with the others meanwhile.
- **Checkpoints** hold θ̃, the strategy's state and each agent's count of answered requests;
  on resuming, every agent gets a fresh request from the checkpoint's θ̃. Work in flight (and
  updates queued but not yet aggregated) when a run was killed is lost.
- **Agent hosts** (``agent.count > 1``) are refused: one ``Train`` per host cannot carry
  its agents' requests of different rounds.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import torch

from fedhpg.common.records.types import EvaluationStats
from fedhpg.server.buffered import BufferedCoordinator, BufferedSchedule, InFlight
from fedhpg.server.coordinator import should_evaluate
from fedhpg.server.pools.zmq_pool import ZmqAgentPool

logger = logging.getLogger(__name__)


class ZmqBufferedCoordinator(BufferedCoordinator):
    """Buffered rounds over :class:`ZmqAgentPool`'s per-agent requests."""

    pool: ZmqAgentPool  # type: ignore[assignment]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        saved = self.schedule
        if saved is not None and saved.in_flight:
            logger.warning(
                "the checkpoint's %d in-flight updates (written in process) are not used: "
                "agent processes start afresh from its θ̃",
                len(saved.in_flight),
            )
        self.schedule = BufferedSchedule(
            clock_s=saved.clock_s if saved is not None else 0.0,
            dispatches=dict(saved.dispatches) if saved is not None else {},
            latest=dict(saved.latest) if saved is not None else {},
        )
        """``dispatches``: each agent's count of answered requests (its rounds done)."""
        self._dispatched_at: dict[int, float] = {}
        """Emulated time each agent's open request started at (for ``emulated_clock_s``)."""
        self._waiting: list[int] = []
        """Agents aggregated into a version being evaluated: restarted after it."""

    def _dispatch(self, agents: Sequence[int], version: int, at_s: float) -> None:
        assert self.schedule is not None
        requests = []
        for k in agents:
            requests.append((k, self.schedule.dispatches.get(k, 0) + 1))
            self._dispatched_at[k] = at_s
        self.pool.start_trains(requests, version, self.theta)

    def _next_arrival(self) -> InFlight:
        assert self.schedule is not None
        arrival = self.pool.next_arrival()
        k = arrival.index
        self.schedule.dispatches[k] = arrival.round
        base = torch.from_numpy(arrival.base)
        # a rejected θ_k may not even have θ̃'s shape: it is never aggregated
        delta = torch.zeros_like(base) if arrival.problem is not None else arrival.theta - base
        arrival_s = self._dispatched_at.get(k, self.schedule.clock_s) + arrival.stats.emulated_s
        self.schedule.clock_s = max(self.schedule.clock_s, arrival_s)
        return InFlight(
            agent=k,
            version=arrival.version,
            dispatch=arrival.round,
            arrival_s=arrival_s,
            agent_id=arrival.agent_id,
            theta=arrival.theta,
            stats=arrival.stats,
            delta=delta,
            problem=arrival.problem,
        )

    def _restart(self, version: int, agents: Sequence[int]) -> None:
        if should_evaluate(self.run, version):
            self._waiting = list(agents)  # after the evaluation
            return
        super()._restart(version, agents)

    def _outstanding(self) -> int:
        return self.pool.outstanding()

    def _evaluate(self, version: int) -> dict[str, EvaluationStats]:
        assert self.schedule is not None
        self.pool.drain()
        evaluation = self.pool.evaluate(version, self.theta, self.run.eval.episodes)
        if version < self.run.rounds:  # after the last version nothing more is collected
            self._dispatch(self._waiting, version, self.schedule.clock_s)
        self._waiting = []
        return evaluation
