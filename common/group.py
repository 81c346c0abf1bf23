"""Many logical agents' learning side in one process: what an agent host and the in-process
pool drive, and what the one-agent process drives with a group of one.

Every placement of an agent (one per process, many per host, all in-process) trains it through
:func:`make_agent_group`, so its θ̃ never depends on where it runs. A group computes only the
learning results; device emulation (clocks, sleeping, message costs) stays with its caller,
fed per agent and per local iteration through ``on_iteration``.

Two implementations: :class:`WorkerLoopGroup` (one :class:`LocalWorker` per agent, trained
one after another: every algorithm, policy and environment) and the batched engine of
:mod:`fedhpg.common.batched` (all the group's agents stepped, evaluated and differentiated as
one batch, where the run's algorithm, policy and family allow it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Protocol

import torch

from fedhpg.common.attacks import attack_of
from fedhpg.common.components import agent_profile, planned_budget
from fedhpg.common.config import RunConfig
from fedhpg.common.types import EvaluationStats, LocalResult
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import IterationWork, LocalWorker
from fedhpg.envs.base import EnvVariant

Budgets = Mapping[int, Mapping[str, int]]
"""Agent index -> the fields of its budget the round's plan sets (``agents.plan``)."""
GroupHook = Callable[[int, IterationWork], None]
"""(agent index, that agent's iteration) -> None, after each local iteration of each agent.
It may raise to cancel the round (the agent process's cancellation does)."""


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
        on_iteration: GroupHook | None = None,
        budgets: Budgets | None = None,
    ) -> dict[int, LocalResult]:
        """The round's local updates of ``agents`` (a subset of ``indices``) from θ̃;
        ``budgets``: the server's plan for some of them (fields of their configured budget)."""
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


class WorkerLoopGroup:
    """One :class:`LocalWorker` per agent, built on first use and kept, trained in index
    order: exactly what a lone agent process computes for each of them."""

    def __init__(self, run: RunConfig, variants: Mapping[int, EnvVariant]) -> None:
        self.run = run
        self.variants = variants
        self._workers: dict[int, LocalWorker] = {}

    @property
    def indices(self) -> Sequence[int]:
        return sorted(self.variants)

    def worker(self, index: int) -> LocalWorker:
        if index not in self._workers:
            self._workers[index] = LocalWorker(
                index=index,
                variant=self.variants[index],
                run=self.run,
                profile=agent_profile(self.run, index),
            )
        return self._workers[index]

    @property
    def num_params(self) -> int:
        return self.worker(self.indices[0]).num_params

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        on_iteration: GroupHook | None = None,
        budgets: Budgets | None = None,
    ) -> dict[int, LocalResult]:
        results: dict[int, LocalResult] = {}
        for k in sorted(agents):
            hook = None
            if on_iteration is not None:

                def hook(work: IterationWork, k: int = k) -> None:
                    on_iteration(k, work)

            worker = self.worker(k)
            budget = planned_budget(worker.profile.budget, (budgets or {}).get(k))
            results[k] = worker.train(round_index, theta.clone(), on_iteration=hook, budget=budget)
        return results

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        return {k: self.worker(k).evaluate(round_index, theta, episodes) for k in sorted(agents)}

    def prepare(self) -> None:
        pass  # a worker holds its environment: built for the agents that train, not ahead

    def close(self) -> None:
        for worker in self._workers.values():
            worker.close()
        self._workers.clear()


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
        on_iteration: GroupHook | None = None,
        budgets: Budgets | None = None,
    ) -> dict[int, LocalResult]:
        results: dict[int, LocalResult] = {}
        for part, chosen in self._split(agents):
            if chosen:
                results.update(
                    part.train(
                        round_index, theta, chosen, on_iteration=on_iteration, budgets=budgets
                    )
                )
        return dict(sorted(results.items()))

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
    """The group implementation for the run: the batched engine for the agents it covers
    (FedHPG, MLP categorical policy; an attacking agent is not covered), a loop over
    :class:`LocalWorker` s for the others."""
    if not indices:
        raise ValueError("an agent group needs at least one agent")
    variants = variants_of(run, indices) if variants is None else variants
    from fedhpg.common.batched import batched_group_or_none

    attackers = [k for k in indices if attack_of(run.attack, k) != "none"]
    honest = [k for k in indices if attack_of(run.attack, k) == "none"]
    batched = batched_group_or_none(run, {k: variants[k] for k in honest}) if honest else None
    if batched is None:
        return WorkerLoopGroup(run, {k: variants[k] for k in indices})
    if not attackers:
        return batched
    return SplitGroup(batched, WorkerLoopGroup(run, {k: variants[k] for k in attackers}))
