"""FedHPG in one process: the K agents as one :class:`~fedhpg.common.group.AgentGroup`
driven by the same coordinator.

No sockets; the distributed runtime (one process per agent, or agent hosts) must reproduce
this runner's θ bit for bit, and does: every placement trains through
:func:`~fedhpg.common.group.make_agent_group`. Emulated device time is accounted on a virtual
clock (no sleeping).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from fedhpg.common.components import validate_run
from fedhpg.common.config import RunConfig, agent_id_of
from fedhpg.common.device import DeviceModel, device_for, message_bytes
from fedhpg.common.group import AgentGroup, make_agent_group
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold
from fedhpg.common.types import AgentUpdate, EvaluationStats
from fedhpg.common.variants import run_variants
from fedhpg.common.worker import IterationWork, initial_theta
from fedhpg.envs.base import EnvVariant
from fedhpg.server.coordinator import Coordinator, RoundCallback, RunProgress
from fedhpg.server.pools import RoundAnswers
from fedhpg.server.strategies import make_strategy, validate_strategy
from fedhpg.server.validation import UpdateCheck

logger = logging.getLogger(__name__)


@dataclass
class InProcessPool:
    """Agents as one group on this thread; each round trains the selected agents."""

    group: AgentGroup
    devices: list[DeviceModel]
    """Emulated devices on a virtual clock: time is accounted, never slept."""
    check: UpdateCheck

    @property
    def agent_ids(self) -> list[str]:
        return [agent_id_of(k) for k in range(len(self.devices))]

    def _updates(
        self, round_index: int, theta: torch.Tensor, agents: Sequence[int]
    ) -> list[AgentUpdate]:
        num_params = self.group.num_params
        # The counted clock charges the two messages an agent process would exchange (θ̃
        # down, θ up), so both runtimes agree; the measured clock charges none here, as before.
        message = message_bytes(num_params)
        for k in agents:
            device = self.devices[k]
            device.take_emulated()
            if device.counted:
                device.transmit(message)

        def on_iteration(k: int, work: IterationWork) -> None:
            self.devices[k].spend(
                work.compute_s,
                work.env_steps,
                round_index,
                grad_steps=work.grad_steps,
                num_params=num_params,
            )

        results = self.group.train(round_index, theta, agents, on_iteration=on_iteration)
        updates = []
        for k in agents:
            device = self.devices[k]
            if device.counted:
                device.transmit(message)
            stats = dataclasses.replace(
                results[k].stats,
                emulated_s=device.take_emulated(),
                speed=device.speed_at(round_index),
            )
            updates.append(
                AgentUpdate(
                    agent_index=k, agent_id=agent_id_of(k), theta=results[k].theta, stats=stats
                )
            )
        return updates

    def train(self, round_index: int, theta: torch.Tensor, agents: Sequence[int]) -> RoundAnswers:
        broadcast = theta.detach().numpy()
        updates, failures = [], {}
        for update in self._updates(round_index, theta, sorted(agents)):
            problem = self.check.problem(update.theta.numpy(), update.stats, broadcast)
            if problem is None:
                updates.append(update)
            else:
                logger.warning("rejected the update of %s: %s", update.agent_id, problem)
                failures[update.agent_id] = problem
        return RoundAnswers(updates=updates, failures=failures)

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]:
        agents = range(len(self.devices))
        evaluations = self.group.evaluate(round_index, theta, episodes, agents)
        return {agent_id_of(k): evaluations[k] for k in agents}

    def close(self) -> None:
        self.group.close()


def make_in_process_pool(run: RunConfig, variants: list[EnvVariant]) -> InProcessPool:
    pin_malloc_mmap_threshold()
    indices = list(range(len(variants)))
    group = make_agent_group(run, indices, variants=dict(enumerate(variants)))
    return InProcessPool(
        group=group,
        devices=[dataclasses.replace(device_for(run, k), virtual_clock=True) for k in indices],
        check=UpdateCheck(num_params=group.num_params, max_update_norm=run.server.max_update_norm),
    )


def run_in_process(
    run: RunConfig,
    *,
    on_round: list[RoundCallback] | None = None,
    theta: torch.Tensor | None = None,
    progress: RunProgress | None = None,
) -> torch.Tensor:
    """Run the whole federation here and return the final θ̃_T. ``theta`` and ``progress``
    continue a run (a checkpoint's θ̃ and rounds done; the caller keeps ``progress``)."""
    validate_run(run)
    validate_strategy(run)
    variants = run_variants(run)
    pool = make_in_process_pool(run, variants)
    try:
        coordinator = Coordinator(
            run=run,
            pool=pool,
            strategy=make_strategy(run.strategy),
            theta=initial_theta(variants[0], run) if theta is None else theta,
            progress=progress,
            on_round=on_round,
        )
        return coordinator.run_rounds()
    finally:
        pool.close()
