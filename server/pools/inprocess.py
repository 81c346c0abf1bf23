"""FedHPG in one process: K :class:`LocalWorker` s driven by the same coordinator.

No sockets; the distributed runtime must reproduce this runner's θ bit for bit. Emulated
device time is accounted on a virtual clock (no sleeping).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from fedhpg.common.components import agent_profile, validate_run
from fedhpg.common.config import RunConfig, agent_id_of
from fedhpg.common.device import DeviceModel, device_for, message_bytes
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold
from fedhpg.common.types import AgentUpdate, EvaluationStats
from fedhpg.common.variants import run_variants
from fedhpg.common.worker import IterationWork, LocalWorker, initial_theta
from fedhpg.envs.base import EnvVariant
from fedhpg.server.coordinator import Coordinator, RoundCallback, RunProgress
from fedhpg.server.pools import RoundAnswers
from fedhpg.server.strategies import make_strategy, validate_strategy
from fedhpg.server.validation import UpdateCheck

logger = logging.getLogger(__name__)


@dataclass
class InProcessPool:
    """Agents as plain objects; each update is computed on this thread, in agent order."""

    workers: list[LocalWorker]
    devices: list[DeviceModel]
    """Emulated devices on a virtual clock: time is accounted, never slept."""
    check: UpdateCheck

    @property
    def agent_ids(self) -> list[str]:
        return [agent_id_of(w.index) for w in self.workers]

    def _train_one(self, k: int, round_index: int, theta: torch.Tensor) -> AgentUpdate:
        worker, device = self.workers[k], self.devices[k]
        device.take_emulated()
        # The counted clock charges the two messages an agent process would exchange (θ̃
        # down, θ up), so both runtimes agree; the measured clock charges none here, as before.
        message = message_bytes(worker.num_params)
        if device.counted:
            device.transmit(message)

        def on_iteration(work: IterationWork) -> None:
            device.spend(
                work.compute_s,
                work.env_steps,
                round_index,
                grad_steps=work.grad_steps,
                num_params=worker.num_params,
            )

        result = worker.train(round_index, theta.clone(), on_iteration=on_iteration)
        if device.counted:
            device.transmit(message)
        stats = dataclasses.replace(
            result.stats, emulated_s=device.take_emulated(), speed=device.speed_at(round_index)
        )
        return AgentUpdate(agent_index=k, agent_id=agent_id_of(k), theta=result.theta, stats=stats)

    def train(self, round_index: int, theta: torch.Tensor, agents: Sequence[int]) -> RoundAnswers:
        broadcast = theta.detach().numpy()
        updates, failures = [], {}
        for k in sorted(agents):
            update = self._train_one(k, round_index, theta)
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
        return {
            agent_id_of(w.index): w.evaluate(round_index, theta, episodes) for w in self.workers
        }

    def close(self) -> None:
        for worker in self.workers:
            worker.close()


def make_in_process_pool(run: RunConfig, variants: list[EnvVariant]) -> InProcessPool:
    pin_malloc_mmap_threshold()
    profiles = [agent_profile(run, k) for k in range(len(variants))]
    workers = [
        LocalWorker(index=k, variant=variant, run=run, profile=profiles[k])
        for k, variant in enumerate(variants)
    ]
    return InProcessPool(
        workers=workers,
        devices=[
            dataclasses.replace(device_for(run, k), virtual_clock=True)
            for k in range(len(variants))
        ],
        check=UpdateCheck(
            num_params=workers[0].num_params, max_update_norm=run.server.max_update_norm
        ),
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
