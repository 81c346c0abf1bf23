"""An agent host: one process serving the logical agents ``agent.first`` .. ``first+count-1``.

It is an :class:`~fedhpg.agent.process.AgentProcess` in everything but what it says and
trains: one DEALER socket, one registration (``HostHello``: the range, the environment spaces
computed once, one digest of the range's variants), one heartbeat for all its agents, one
``TrainBatch`` per round (θ̃ once, the host's selected agents) answered by
ceil(A / :func:`~fedhpg.common.wire.transport.answers_per_message`) ``UpdateBatch`` es. Every
agent trains through one :func:`~fedhpg.common.group.make_agent_group` of the whole range, as
in the one-agent process and the in-process pool, so θ̃ does not depend on the placement.

Device emulation runs on a virtual clock per logical agent: the emulated time of each agent
(measured or counted, ``agents.clock``) is accounted in its own ``emulated_s``, never slept —
a host of 500 agents cannot sleep 500 devices' time on one thread. A host's answers therefore
arrive when its real compute is done, whatever the emulated speeds; a run that needs the
sleeping emulation (wall-clock deadlines against emulated slowness) uses one process per agent.
"""

from __future__ import annotations

import dataclasses
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
from fedhpg.common.device import DeviceModel, device_for, message_bytes
from fedhpg.common.group import AgentGroup, make_agent_group
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
from fedhpg.common.worker import IterationWork

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
        group = make_agent_group(run, self.indices, variants=self.variants)
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
        if not set(agents) <= set(self.variants):
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
        num_params = self.group.num_params
        message = message_bytes(num_params)
        for k in agents:  # the request's one-way latency (and transfer), per logical agent
            self.devices[k].take_emulated()
            self.devices[k].transmit(message)

        def on_iteration(k: int, work: IterationWork) -> None:
            if job.cancel.is_set():
                raise Cancelled
            self.devices[k].spend(
                work.compute_s,
                work.env_steps,
                request.round,
                grad_steps=work.grad_steps,
                num_params=num_params,
            )

        planned = dict(zip(request.agents, request.budgets, strict=True)) if request.budgets else {}
        results = self.group.train(
            request.round, theta, agents, on_iteration=on_iteration, budgets=planned
        )
        # Each answer leaves with the batch: the host's wall time on the round is each one's.
        wall_s = time.perf_counter() - started
        emulated, speeds = {}, {}
        for k in agents:
            device = self.devices[k]
            device.transmit(message)  # the answer's
            emulated[k] = device.take_emulated()
            speeds[k] = device.speed_at(request.round)
        per_message = answers_per_message(batch_message_cap(self.max_bytes, num_params), num_params)
        return [
            UpdateBatch(
                round=request.round,
                agents=chunk,
                thetas=np.stack([results[k].theta.numpy() for k in chunk]),
                # the device's fields replaced column-wise, not record by record
                stats=dataclasses.replace(
                    UpdateColumns.of([results[k].stats for k in chunk]),
                    emulated_s=[emulated[k] for k in chunk],
                    local_wall_s=[wall_s] * len(chunk),
                    speed=[speeds[k] for k in chunk],
                ),
            )
            for chunk in _chunks(agents, per_message)
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
