"""An agent host: one process serving the logical agents ``agent.first`` .. ``first+count-1``.

It is an :class:`~fedhpg.agent.process.AgentProcess` in everything but what it says and
trains: one DEALER socket, one registration (``HostHello``: the range, the environment spaces
computed once, one digest of the range's variants), one heartbeat for all its agents, one
``TrainBatch`` per round (θ̃ once, the host's selected agents) answered by
ceil(A / :func:`~fedhpg.common.wire.transport.answers_per_message`) ``UpdateBatch`` es. Every
agent trains through one :func:`~fedhpg.common.group.make_agent_group` of the whole range, as
in the one-agent process and the in-process pool, so θ̃ does not depend on the placement.

Device emulation runs on a virtual clock per logical agent: the emulated time of each agent
(measured or counted, ``agents.clock``) is accounted, never slept — a host of 500 agents
cannot sleep 500 devices' time on one thread. The host takes its round as columns
(:func:`~fedhpg.common.round_columns.train_columns`) and prices all its agents' iterations
at once (:class:`~fedhpg.common.device.DeviceColumns`), to the bit what each agent's own
``DeviceModel`` gives in a one-agent process. A host's answers therefore
arrive when its real compute is done, whatever the emulated speeds; a run that needs the
sleeping emulation (wall-clock deadlines against emulated slowness) uses one process per agent.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from fedhpg.agent.process import AgentFailure, AgentProcess, Cancelled, Job, Request
from fedhpg.common.config import RunConfig, host_id_of
from fedhpg.common.device import DeviceColumns, DeviceModel, device_for, message_bytes
from fedhpg.common.group import AgentGroup, make_agent_group
from fedhpg.common.round_columns import train_columns
from fedhpg.common.runtime import timeline
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold, tune_malloc_for
from fedhpg.common.variants import range_digest, variant_digest, variants_of
from fedhpg.common.wire.protocol import (
    MAX_BATCH_ANSWERS,
    EvaluateBatch,
    EvaluationBatch,
    HostHello,
    HostWelcome,
    Message,
    TrainBatch,
    UpdateBatch,
    UpdateColumns,
)
from fedhpg.common.wire.transport import answers_per_message, batch_message_cap

logger = logging.getLogger(__name__)


class AgentHost(AgentProcess):
    """The logical agents ``run.agent.first`` .. ``first + count - 1`` over one connection."""

    def __init__(self, run: RunConfig) -> None:
        first, count = run.agent.first, run.agent.count
        assert first is not None  # validate() checked the range against agents.num_agents
        self.own = run
        self.first, self.count = first, count
        self.indices = list(range(first, first + count))
        self.index = first  # what the base class's logging and key lookup name
        self.agent_id = host_id_of(first, count, run.agent.id)
        pin_malloc_mmap_threshold()
        self.variants = variants_of(run, self.indices)  # the range's rows, drawn in one go
        variants = self.variants
        self.variant = variants[first]
        self.signature = self.variant.signature()  # the run's spaces: the same for every agent
        self.digest = range_digest([variant_digest(run, variants[k]) for k in self.indices])
        self.devices = self._devices(run)
        self.device = self.devices[first]
        self._init_io(run)

    def _devices(self, run: RunConfig) -> dict[int, DeviceModel]:
        return {k: replace(device_for(run, k), virtual_clock=True) for k in self.indices}

    # -- registration -----------------------------------------------------------------------

    def _hello(self) -> Message:
        return HostHello(
            host_id=self.agent_id,
            first=self.first,
            count=self.count,
            env_signature=self.signature,
            variant_digest=self.digest,
            profile={"pid": os.getpid(), "agents": self.count},
        )

    def _is_welcome(self, message: Message | None) -> bool:
        return (
            isinstance(message, HostWelcome)
            and message.first == self.first
            and message.count == self.count
        )

    def _make_group(self, run: RunConfig) -> AgentGroup:
        self.devices = self._devices(run)
        # the range's devices, row k - first agent k's: what a round prices
        self.device_columns = DeviceColumns([self.devices[k] for k in self.indices])
        group = make_agent_group(run, self.indices, variants=self.variants)
        group.prepare()  # every agent's constants now, not inside the rounds that select it
        tune_malloc_for(group)
        return group

    def _log_registered(self, run: RunConfig, run_id: str) -> None:
        logger.debug(
            "%s registered agents %d..%d in run %s",
            self.agent_id,
            self.first,
            self.first + self.count - 1,
            run_id,
        )

    def _request_types(self) -> tuple[type, ...]:
        return (TrainBatch, EvaluateBatch)

    # -- jobs -------------------------------------------------------------------------------

    def _work(self, job: Job) -> list[Message]:
        assert self.group is not None
        request = job.request
        assert isinstance(request, TrainBatch | EvaluateBatch)
        agents = sorted(set(request.agents))
        if agents and not (self.first <= agents[0] and agents[-1] < self.first + self.count):
            raise AgentFailure(f"the server asked for agents outside {self.agent_id}'s range")
        theta = torch.from_numpy(np.array(request.theta))
        if isinstance(request, EvaluateBatch):
            evaluations = self.group.evaluate(request.round, theta, request.episodes, agents)
            return [
                EvaluationBatch(
                    round=request.round, agents=chunk, stats=[evaluations[k] for k in chunk]
                )
                for chunk in _chunks(agents, MAX_BATCH_ANSWERS)
            ]
        started = time.perf_counter()

        def interrupt() -> None:
            if job.cancel.is_set():
                raise Cancelled

        planned = dict(zip(request.agents, request.budgets, strict=True)) if request.budgets else {}
        timeline.mark(self.agent_id, "work-start", request.round)
        trained = train_columns(
            self.group, request.round, theta, agents, budgets=planned, interrupt=interrupt
        )
        timeline.mark(self.agent_id, "trained", request.round)
        num_params = trained.thetas.shape[1]
        rows = np.asarray(trained.agents, dtype=np.int64) - self.first
        emulated, speeds = self.device_columns.round(
            rows,
            request.round,
            message_bytes(num_params),
            trained.iterations,
            num_params,
        )
        # Each answer leaves with the batch: the host's wall time on the round is each one's.
        wall_s = time.perf_counter() - started
        stats = UpdateColumns(
            trajectories=trained.trajectories.tolist(),
            env_steps=trained.env_steps.tolist(),
            compute_s=trained.compute_s.tolist(),
            train_return=trained.train_return.tolist(),
            grad_clipped=trained.grad_clipped.tolist(),
            emulated_s=emulated.tolist(),
            speed=speeds.tolist(),
            local_wall_s=[wall_s] * len(rows),
            algorithm=trained.algorithm,
        )
        per_message = answers_per_message(batch_message_cap(self.max_bytes, num_params), num_params)
        return [
            UpdateBatch(
                round=request.round,
                agents=trained.agents[start : start + per_message],
                thetas=trained.thetas[start : start + per_message],
                stats=stats[start : start + per_message],
            )
            for start in range(0, len(rows), per_message)
        ]

    def _resend(self, answers: list[Message], request: Request) -> list[Message]:
        """The rows of the last answers that ``request`` asks for again (a rejoined host is
        asked only for the agents whose answers the server has not got)."""
        wanted = set(request.agents) if isinstance(request, TrainBatch | EvaluateBatch) else set()
        again: list[Message] = []
        for answer in answers:
            if not isinstance(answer, UpdateBatch | EvaluationBatch):
                continue
            rows = [i for i, k in enumerate(answer.agents) if k in wanted]
            if not rows:
                continue
            picked: dict[str, Any] = {"agents": [answer.agents[i] for i in rows]}
            if isinstance(answer, UpdateBatch):
                picked["thetas"] = answer.thetas[rows]
                picked["stats"] = answer.stats.take(rows)
            else:
                picked["stats"] = [answer.stats[i] for i in rows]
            again.append(replace(answer, **picked))
        return again

    def run(self) -> None:
        started = time.monotonic()
        try:
            self.adopt(self.register())
            logger.info(
                "%s: %d agents registered in %.2f s",
                self.agent_id,
                self.count,
                time.monotonic() - started,
            )
            self.serve()
        finally:
            self.close()


def _chunks(agents: Sequence[int], size: int) -> list[list[int]]:
    return [list(agents[i : i + size]) for i in range(0, len(agents), size)]
