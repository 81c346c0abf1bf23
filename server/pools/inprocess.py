"""FedHPG in one process: the pool of one :class:`AgentGroup` of all K agents.

No sockets; the distributed runtime must reproduce this pool's θ bit for bit
(:func:`fedhpg.server.assembly.run_in_process` runs a federation over it). Emulated
device time is accounted on a virtual clock (no sleeping). Agents cost memory only once asked:
the group builds an agent's worker on first use, and its device is made then too, so a run of
K = 10 000 agents with 1 000 per round starts with none of them built.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.ids import agent_id_of
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.common.heterogeneity.device import DeviceColumns, DeviceModel, device_for, message_bytes
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.group import AgentGroup, make_agent_group
from fedhpg.common.privacy import fixedpoint
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy, contribution, redacted
from fedhpg.common.privacy.secagg import SecAggError, SecAggRound, fewest_inputs
from fedhpg.common.privacy.session import LocalSecAgg
from fedhpg.common.records.types import EvaluationStats, RoundResult
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold, tune_malloc_for
from fedhpg.envs.base import EnvVariant
from fedhpg.server.pools import RoundAnswers, SecureSum
from fedhpg.server.validation import Rejection, UpdateCheck

logger = logging.getLogger(__name__)


class InProcessPool:
    """All K agents as one group on this thread; updates come back in agent order."""

    def __init__(self, run: RunConfig, group: AgentGroup, *, num_params: int) -> None:
        self.run = run
        self.group = group
        self.num_params = num_params
        # under secure aggregation the server sees no θ_k: max_update_norm bounds the round's
        # average step instead (server/secure_sum.py), as with agent processes
        secure = run.privacy.mode in ("secagg", "dp_secagg")
        bound = None if secure else run.server.max_update_norm
        self.check = UpdateCheck(num_params=num_params, max_update_norm=bound)
        self._devices: dict[int, DeviceModel] = {}
        self.secure = LocalSecAgg(run)

    @property
    def agent_ids(self) -> list[str]:
        return [agent_id_of(k) for k in self.group.indices]

    def device(self, k: int) -> DeviceModel:
        """Agent k's emulated device on a virtual clock (time accounted, never slept), made
        when first asked and kept: its clock carries over between rounds."""
        if k not in self._devices:
            self._devices[k] = dataclasses.replace(device_for(self.run, k), virtual_clock=True)
        return self._devices[k]

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
        if while_training is not None:  # the agents train on this thread: nothing overlaps
            while_training()
        result, problems = self.checked_result(round_index, theta, agents, budgets=budgets)
        accepted = [i for i, problem in enumerate(problems) if problem is None]
        failures = {
            agent_id_of(k): problem
            for k, problem in zip(result.agents, problems, strict=True)
            if problem is not None
        }
        answers = RoundAnswers(result=result.taking(accepted), failures=failures)
        if ROUND_POLICIES.get(self.run.server.round_policy).quorum:
            answers = self._at_deadline(answers)
        if self.run.privacy.mode != "none":
            answers = dataclasses.replace(answers, result=redacted(answers.result))
        if private is not None:
            return self._securely(round_index, theta, answers, sorted(agents), private)
        return answers

    def _securely(
        self,
        round_index: int,
        theta: torch.Tensor,
        answers: RoundAnswers,
        selected: list[int],
        private: RoundPrivacy,
    ) -> RoundAnswers:
        """The round's accepted updates summed by secure aggregation, as agent processes would
        (each agent's keys, shares, masked input and unmasking, here on one thread): the
        server's side sees the sum only. A rejected update or a straggler takes part in the
        key exchange and drops out before its input, as over the wire."""
        accepted = answers.result
        stripped = accepted.without_thetas(theta.detach().numpy())
        contributing = {k: i for i, k in enumerate(accepted.agents)}
        length = theta.numel() + EXTRA
        advertised = {k: self.secure.advertise(round_index, k) for k in selected}
        try:
            setup = self.secure.setup(
                round_index,
                len(selected),
                length,
                {k: self.secure.agent(k).channel_public for k in selected},
                {k: advert[0] for k, advert in advertised.items()},
                {k: advert[1] for k, advert in advertised.items()},
                {k: advert[2] for k, advert in advertised.items()},
            )
        except SecAggError as error:
            empty = SecureSum(
                total=np.zeros(0), inputs=0, participants=len(selected), failed=str(error)
            )
            return dataclasses.replace(answers, result=stripped, secure=empty)
        server = SecAggRound(setup)
        for k in selected:
            server.add_keys(k, self.secure.agent(k).share_keys(setup))
        scale = fixedpoint.scale_for(len(selected), max(private.bound, 1.0))
        noise = self.secure.noise
        for k in selected:
            if k not in contributing:
                continue
            i = contributing[k]
            row = contribution(
                torch.from_numpy(accepted.thetas[i]) - theta,
                accepted.stats.trajectories[i],
                private,
                noise(round_index, k),
            )
            words = fixedpoint.encode(row, scale, max(private.bound, 1.0))
            server.add_masked(k, self.secure.agent(k).mask(round_index, words, *server.routed(k)))
        dropped, included = server.unmask_request()
        privacy = self.run.privacy
        fewest = fewest_inputs(privacy.mode, privacy.secagg, len(selected))

        def failed(reason: str) -> RoundAnswers:
            empty = SecureSum(
                total=np.zeros(0), inputs=0, participants=len(selected), failed=reason
            )
            return dataclasses.replace(answers, result=stripped, secure=empty)

        if len(included) < fewest:  # checked before any input is unmasked
            return failed(
                f"{len(included)} inputs arrived, fewer than the {fewest} the round needs "
                "(privacy.secagg.dropout): nothing was unmasked"
            )
        for k in included:
            server.add_reveal(k, self.secure.agent(k).reveal(round_index, dropped, included))
        try:
            total = fixedpoint.decode(server.total(fewest=fewest), scale)
        except SecAggError as error:
            return failed(f"secure aggregation failed: {error}")
        return dataclasses.replace(
            answers,
            result=stripped,
            secure=SecureSum(total=total, inputs=len(included), participants=len(selected)),
        )

    def _at_deadline(self, answers: RoundAnswers) -> RoundAnswers:
        """The deadline policy on the emulated clock (nothing here waits on the wall clock):
        the round closes at ``round_deadline_s`` emulated seconds, or later when fewer than
        ``min_agents`` updates had arrived by then, at the arrival that makes them enough;
        updates arriving after it are stragglers, as with agent processes."""
        settings = self.run.server
        result = answers.result
        emulated = result.stats.emulated_s
        arrivals = sorted(emulated)
        enough = arrivals[min(settings.min_agents, len(arrivals)) - 1] if arrivals else 0.0
        closes = max(settings.round_deadline_s, enough)
        kept = [i for i, seconds in enumerate(emulated) if seconds <= closes]
        late = [agent_id_of(k) for k, s in zip(result.agents, emulated, strict=True) if s > closes]
        return dataclasses.replace(answers, result=result.taking(kept), stragglers=late)

    def checked_result(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Mapping[int, Mapping[str, int]] | None = None,
    ) -> tuple[RoundResult, list[Rejection | None]]:
        """Every selected agent's update of ``round_index`` from θ̃, rows in agent order,
        with why the update check rejects each (None: accepted)."""
        selected = sorted(agents)
        trained = self.group.train(round_index, theta, selected, budgets=budgets)
        devices = DeviceColumns([self.device(k) for k in selected])
        # The counted clock charges the two messages an agent process would exchange (θ̃
        # down, θ up), so both runtimes agree; the measured clock charges none here.
        emulated, speeds = devices.round(
            np.arange(len(selected)),
            round_index,
            message_bytes(self.num_params),
            trained.iterations,
            self.num_params,
            messages=devices.counted,
        )
        result = trained.result.with_stats(emulated_s=emulated.tolist(), speed=speeds.tolist())
        problems = self.check.problems(result.thetas, result.stats, theta.detach().numpy())
        for k, problem in zip(selected, problems, strict=True):
            if problem is not None:
                logger.warning("rejected the update of %s: %s", agent_id_of(k), problem)
        return result, problems

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]:
        evaluations = self.group.evaluate(round_index, theta, episodes, self.group.indices)
        return {agent_id_of(k): stats for k, stats in evaluations.items()}

    def secure_participants(self, agents: Sequence[int]) -> list[int]:
        """Every agent is here: all of them."""
        return sorted(agents)

    def counters(self) -> dict[str, int]:
        """Nothing goes wrong between agents on one thread: no counters."""
        return {}

    def close(self) -> None:
        self.group.close()


def make_in_process_pool(
    run: RunConfig, variants: Sequence[EnvVariant] | None = None
) -> InProcessPool:
    """The pool of the run's K agents (``variants``: the K variants if already at hand)."""
    pin_malloc_mmap_threshold()
    indices = range(run.agents.num_agents)
    by_index = dict(enumerate(variants)) if variants is not None else variants_of(run, indices)
    group = make_agent_group(run, list(indices), by_index)
    tune_malloc_for(group)
    return InProcessPool(run, group, num_params=group.num_params)
