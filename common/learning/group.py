"""Many logical agents' learning side in one process: what an agent host and the in-process
pool drive, and what the one-agent process drives with a group of one.

Every placement of an agent (one per process, many per host, all in-process) trains it through
:func:`make_agent_group`, so its θ̃ never depends on where it runs. A group computes only the
learning results (a :class:`~fedhpg.common.records.round_columns.TrainedRound`); device emulation
(clocks, sleeping, message costs) stays with its caller, which prices the round's iterations.

:class:`EngineGroup` runs the run's algorithm over rows of agents on the engine
(:mod:`fedhpg.common.learning.engine`: every algorithm, policy and environment family); the compiled
CartPole engine of :mod:`fedhpg.common.learning.batched` trains FedHPG's honest agents where it
applies.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.attacks import corrupt_rows
from fedhpg.common.learning.batched import compiled_agents, compiled_backend
from fedhpg.common.learning.components import resolve_algorithm
from fedhpg.common.learning.engine.engine import Engine, engine_settings
from fedhpg.common.learning.engine.round import Tally
from fedhpg.common.records.round_columns import TrainedRound
from fedhpg.common.records.types import EvaluationStats, RoundResult, UpdateColumns
from fedhpg.envs.base import EnvVariant

if TYPE_CHECKING:
    from fedhpg.common.learning.engine.memory import RoundPlan

logger = logging.getLogger(__name__)

Budgets = Mapping[int, Mapping[str, int]]
"""Agent index -> the fields of its budget the round's plan sets (``agents.plan``)."""
Interrupt = Callable[[], None]
"""Called after each local iteration; it may raise to cancel the round (an agent process's
does when the server supersedes the request)."""


RECENT_PLANS = 8
"""Round plans a group keeps (the lists of agents its rounds repeat)."""

TIMING_STATS = ("engine_sample_s", "engine_gradient_s")
"""Algorithm statistics that are CPU times (of ``compute_s``: sampling, the rest): they vary
from run to run like ``compute_s`` itself."""


class AgentGroup(Protocol):
    """The learning side of the logical agents ``indices`` of one run."""

    @property
    def indices(self) -> Sequence[int]: ...

    @property
    def num_params(self) -> int: ...

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Budgets | None = None,
        interrupt: Interrupt | None = None,
    ) -> TrainedRound:
        """The round's local updates of ``agents`` (a subset of ``indices``) from θ̃;
        ``budgets``: the server's plan for some of them (fields of their configured budget);
        ``interrupt``: called after each local iteration, it may raise to cancel the round."""
        ...

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        """The unified policy's return and success in each agent's environment."""
        ...

    def prepare(self) -> None:
        """Compute now what the group would compute of each agent on its first round (an
        agent host calls it once, at registration, so that rounds do not pay for it)."""
        ...

    def close(self) -> None: ...


class EngineGroup:
    """The run's algorithm over rows of agents on the engine (:mod:`fedhpg.common.learning.engine`):
    every algorithm, policy and environment family; each agent's numbers depend on it alone,
    so a group of one, a host of 500 and the in-process pool give it the same θ."""

    LARGE_TEMPORARIES = True
    """Megabytes of buffers every round (common/runtime/memory.py)."""

    def __init__(
        self, run: RunConfig, variants: Mapping[int, EnvVariant], *, compiled: bool = False
    ) -> None:
        self.run = run
        self.variants = variants
        self.engine = Engine(run, variants, backend=compiled_backend if compiled else None)
        self.algorithm, self.params = resolve_algorithm(run)
        self._plans: dict[tuple[int, ...], RoundPlan] = {}
        """The plans of rounds of agents running their own budgets (a round repeats them)."""

    @property
    def indices(self) -> Sequence[int]:
        return sorted(self.variants)

    @property
    def num_params(self) -> int:
        return self.engine.policy.num_params

    def plan(
        self, agents: Sequence[int], budgets: Budgets | None = None, episodes: int | None = None
    ) -> RoundPlan:
        """The round's ``agents`` (ascending) in chunks that fit the device's memory: each
        holds its budget's trajectories at once (``episodes`` each for an evaluation)."""
        engine = self.engine
        own = episodes is None and not budgets
        if own and tuple(agents) in self._plans:
            return self._plans[tuple(agents)]
        if episodes is None:
            chosen = engine.round_budgets(agents, budgets)
            copies = [self.algorithm.held_trajectories(budget) for budget in chosen]
            horizons = [engine.horizon(k) for k in agents]
        else:
            copies = [episodes] * len(agents)
            horizons = [self.run.eval.horizon or engine.horizon(k) for k in agents]
        plan = engine.plan(agents, copies, horizons)
        if own:
            if len(self._plans) >= RECENT_PLANS:
                self._plans.clear()
            self._plans[tuple(agents)] = plan
        return plan

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Budgets | None = None,
        interrupt: Interrupt | None = None,
    ) -> TrainedRound:
        """The round of ``agents``, chunk after chunk of :meth:`plan` (an agent's numbers do
        not depend on the chunk it is in); only the θ rows and the statistics leave the
        device."""
        order = sorted(agents)
        plan = self.plan(order, budgets)
        if len(plan.chunks) > 1:
            logger.debug("round %d: %s", round_index, plan.describe())
        engine = self.engine
        honest: list[torch.Tensor] = []
        tallies: list[Tally] = []
        for chunk in plan.chunks:
            with engine_settings(engine.device):
                rows = engine.begin(
                    round_index, theta, order[chunk.start : chunk.stop], budgets, interrupt
                )
                update = self.algorithm.local_update(rows, self.run.algo, self.params)
                honest.append(update.cpu())  # detached below, with the attack's rows
            tallies.append(rows.tally)
        sent = corrupt_rows(
            self.run.attack,
            theta,
            honest[0] if len(honest) == 1 else torch.cat(honest),
            order,
            seed=self.run.seed,
            round_index=round_index,
        )
        tally = Tally.concatenated(tallies)
        stats = UpdateColumns.filled(
            len(order),
            trajectories=tally.trajectories,
            env_steps=tally.env_steps,
            compute_s=tally.compute_s,
            train_return=tally.return_sum / np.maximum(tally.trajectories, 1),
            grad_clipped=tally.clipped,
            algorithm={
                **{
                    name: [None if math.isnan(v) else v for v in values.tolist()]
                    for name, values in tally.algorithm.items()
                },
                # where the engine's time went, per agent (its share by env steps)
                TIMING_STATS[0]: tally.sample_s.tolist(),
                TIMING_STATS[1]: (tally.compute_s - tally.sample_s).tolist(),
            },
        )
        result = RoundResult(
            round=round_index,
            agents=order,
            thetas=sent.detach().numpy().astype(np.float32, copy=False),
            stats=stats,
        )
        return TrainedRound(result=result, iterations=tally.work)

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        order = sorted(agents)
        stats: dict[int, EvaluationStats] = {}
        for chunk in self.plan(order, episodes=episodes).chunks:
            with engine_settings(self.engine.device):
                stats.update(
                    self.engine.evaluate(
                        round_index, theta, episodes, order[chunk.start : chunk.stop]
                    )
                )
        return stats

    def prepare(self) -> None:
        self.engine.prepare()

    def close(self) -> None:
        self.engine.close()


class SplitGroup:
    """Two groups side by side (the engine's honest agents, the loop's attackers): each agent
    is trained by the one that holds it, exactly as it would be alone."""

    def __init__(self, *parts: AgentGroup) -> None:
        self.parts = parts

    @property
    def indices(self) -> Sequence[int]:
        return sorted(k for part in self.parts for k in part.indices)

    @property
    def num_params(self) -> int:
        return self.parts[0].num_params

    def _split(self, agents: Sequence[int]) -> list[tuple[AgentGroup, list[int]]]:
        mine = [(part, set(part.indices)) for part in self.parts]
        return [(part, [k for k in agents if k in held]) for part, held in mine]

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Budgets | None = None,
        interrupt: Interrupt | None = None,
    ) -> TrainedRound:
        return TrainedRound.concatenated(
            [
                part.train(round_index, theta, chosen, budgets=budgets, interrupt=interrupt)
                for part, chosen in self._split(agents)
                if chosen
            ]
        )

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        stats: dict[int, EvaluationStats] = {}
        for part, chosen in self._split(agents):
            if chosen:
                stats.update(part.evaluate(round_index, theta, episodes, chosen))
        return dict(sorted(stats.items()))

    def prepare(self) -> None:
        for part in self.parts:
            part.prepare()

    def close(self) -> None:
        for part in self.parts:
            part.close()


def make_agent_group(
    run: RunConfig, indices: Sequence[int], variants: Mapping[int, EnvVariant] | None = None
) -> AgentGroup:
    """The group for the run's agents ``indices``: an engine on the compiled backend for the
    agents it serves (:func:`fedhpg.common.learning.batched.compiled_agents`), an engine on torch
    for the others; each agent's backend follows from the agent alone, never from its company."""
    if not indices:
        raise ValueError("an agent group needs at least one agent")
    variants = variants_of(run, indices) if variants is None else variants
    compiled = compiled_agents(run, {k: variants[k] for k in indices})
    parts = [
        EngineGroup(run, {k: variants[k] for k in indices if (k in compiled) == on}, compiled=on)
        for on in (True, False)
        if any((k in compiled) == on for k in indices)
    ]
    return parts[0] if len(parts) == 1 else SplitGroup(*parts)
