"""The engine of a group of agents: their constants, the memory plan, and rounds.

:meth:`Engine.begin` returns a :class:`~fedhpg.common.learning.engine.round.Round`: the rows of a
round's agents (θ̃ copies, budgets) with the primitives their algorithm's loop is written
with, on the group's backend (:class:`~fedhpg.common.learning.engine.backend.Backend`: torch on
``algo.device``, or the compiled CartPole backend on the CPU), chosen once here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.variants import discount, training_horizon
from fedhpg.common.learning.components import AgentProfile, agent_profile, planned_budget
from fedhpg.common.learning.engine.backend import Backend
from fedhpg.common.learning.engine.devices import check_device, deterministic_off_cpu
from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.host_arrays import HostArrays
from fedhpg.common.learning.engine.memory import RoundPlan, StepBytes, memory_budget, plan_round
from fedhpg.common.learning.engine.policy_rows import PolicyRows
from fedhpg.common.learning.engine.round import BudgetRows, Interrupt, Round, RowConstants
from fedhpg.common.learning.engine.torch_backend import TorchBackend
from fedhpg.common.learning.policies import Policy
from fedhpg.common.learning.randomness import Purpose
from fedhpg.common.learning.worker import policy_and_spaces
from fedhpg.common.records.types import EvaluationStats
from fedhpg.envs.base import EnvVariant


@contextmanager
def one_thread() -> Iterator[None]:
    """Run the enclosed maths on one CPU thread. Several threads would split reductions (a
    scatter-add's, a matrix product's) by the thread count, so the floats of an agent would
    depend on the process's thread setting: an agent process (one thread) and the in-process
    pool (as many as the machine) must compute the same θ."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def engine_settings(device: torch.device) -> AbstractContextManager[None]:
    """What every use of the engine runs under: one CPU thread (:func:`one_thread`) and, off
    the CPU, torch's deterministic algorithms (:func:`deterministic_off_cpu`), so that an
    agent's floats depend neither on the process nor on its company; the caller's settings
    come back after. An agent process already runs so on the CPU: nothing to change."""
    if device.type == "cpu" and torch.get_num_threads() == 1:
        return nullcontext()
    return _settings(device)


@contextmanager
def _settings(device: torch.device) -> Iterator[None]:
    with one_thread(), deterministic_off_cpu(device):
        yield


BackendAround = Callable[[Policy, dict[int, EnvVariant], TorchBackend], Backend]
"""(the policy's template, the variants, the engine's torch backend) -> the backend the engine
runs on instead (:func:`fedhpg.common.learning.batched.compiled_backend`)."""


class Engine:
    """The rounds of the agents ``variants`` of one run on one backend: torch, or the one
    ``backend`` builds around it (the compiled one, where the caller checked it serves these
    agents: :func:`fedhpg.common.learning.batched.compiled_agents`)."""

    def __init__(
        self,
        run: RunConfig,
        variants: Mapping[int, EnvVariant],
        *,
        backend: BackendAround | None = None,
    ) -> None:
        self.run = run
        self.variants = dict(variants)
        check_device(run.algo.device)
        self.device = torch.device(run.algo.device)
        first = self.variants[min(self.variants)]
        template, observation_space, action_space = policy_and_spaces(first, run)
        self.policy = PolicyRows(template, self.device)
        torch_backend = TorchBackend(
            run, self.variants, self.policy, (observation_space, action_space), self.device
        )
        family = torch_backend.family()
        self.step_bytes = StepBytes.of(
            observation_space,
            action_space,
            self.policy.num_params,
            self.policy.noise_size,
            self.device,
            step_noise=0 if family is None else family.step_noise,
        )
        self.backend: Backend = (
            torch_backend if backend is None else backend(template, self.variants, torch_backend)
        )
        self.options = EstimatorOptions.of(run.algo)
        self._profiles: dict[int, AgentProfile] = {}
        self._gamma: dict[int, float] = {}
        self._horizon: dict[int, int] = {}
        self._own_budgets: tuple[tuple[int, ...], list[Any]] | None = None
        """The last :meth:`round_budgets` of agents running their own budgets."""
        self._budget_rows: tuple[list[Any], BudgetRows, RowConstants] | None = None
        """For the last list of budgets: its fields as rows and the rows' constants."""
        self._host = HostArrays()
        """Host views of the budget rows the rounds' loops pass back (made once a list)."""

    # -- per-agent constants ----------------------------------------------------------------

    def profile(self, k: int) -> AgentProfile:
        if k not in self._profiles:
            self._profiles[k] = agent_profile(self.run, k)
        return self._profiles[k]

    def gamma(self, k: int) -> float:
        if k not in self._gamma:
            self._gamma[k] = discount(self.run, self.variants[k])
        return self._gamma[k]

    def horizon(self, k: int) -> int:
        if k not in self._horizon:
            self._horizon[k] = training_horizon(self.run, self.variants[k])
        return self._horizon[k]

    def prepare(self) -> None:
        for k in self.variants:
            self.profile(k), self.gamma(k), self.horizon(k)
        self.backend.prepare()

    def close(self) -> None:
        self.backend.close()

    # -- a round ----------------------------------------------------------------------------

    def begin(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        interrupt: Interrupt | None = None,
    ) -> Round:
        """The round of ``agents`` from θ̃ (their budgets planned or their own)."""
        chosen = self.round_budgets(agents, budgets)
        if self._budget_rows is None or self._budget_rows[0] is not chosen:  # a new list
            names = list(vars(chosen[0])) if chosen else []
            values = {name: [int(getattr(b, name)) for b in chosen] for name in names}
            self._budget_rows = (
                chosen,
                BudgetRows(
                    rows={name: torch.tensor(v, dtype=torch.int64) for name, v in values.items()},
                    spans={name: (min(v), max(v)) for name, v in values.items()},
                ),
                self._constants(agents),
            )
        _, budget_rows, constants = self._budget_rows
        return Round(
            backend=self.backend,
            options=self.options,
            seed=self.run.seed,
            round_index=round_index,
            agents=agents,
            theta=self._theta_rows(theta, len(agents)),
            budgets=budget_rows,
            constants=constants,
            interrupt=interrupt,
            host=self._host,
        )

    def _theta_rows(self, theta: torch.Tensor, count: int) -> torch.Tensor:
        """θ̃ [d] as ``count`` float32 rows [count, d] on the device, each its own copy (the
        loop steps them in place); on the host one numpy copy, where torch would take four
        calls (detach, to, expand, clone), each dearer than the copy for a few agents."""
        plain = theta.dtype == torch.float32 and theta.dim() == 1 and not theta.requires_grad
        if plain and self.device.type == "cpu" and theta.device.type == "cpu":
            return torch.from_numpy(np.repeat(theta.numpy()[None], count, axis=0))
        return theta.detach().to(self.device, torch.float32).expand(count, -1).clone()

    def plan(
        self, agents: Sequence[int], copies: Sequence[int], horizons: Sequence[int]
    ) -> RoundPlan:
        """Chunks of ``agents`` (agent i holding ``copies[i]`` trajectories of up to
        ``horizons[i]`` steps at once) that fit ``algo.memory_gib`` on the device
        (``common/learning/engine/memory.py``)."""
        budget = memory_budget(self.device, self.run.algo.memory_gib)
        return plan_round(copies, horizons, self.step_bytes, budget)

    def round_budgets(
        self, agents: Sequence[int], budgets: Mapping[int, Mapping[str, int]] | None = None
    ) -> list[Any]:
        """Each agent's budget for the round: its own, or with the server's plan put in. The
        list is kept, the same object, while the agents repeat and run their own budgets."""
        key = tuple(agents)
        own = not budgets or not any(budgets.get(k) for k in key)
        if own and self._own_budgets is not None and self._own_budgets[0] == key:
            return self._own_budgets[1]
        chosen = [planned_budget(self.profile(k).budget, (budgets or {}).get(k)) for k in key]
        self._own_budgets = (key, chosen) if own else None
        return chosen

    def _constants(self, agents: Sequence[int]) -> RowConstants:
        def row(values: list[Any], dtype: torch.dtype) -> torch.Tensor:
            return torch.tensor(values, dtype=dtype).to(self.device)

        return RowConstants(
            agent=row(list(agents), torch.int64),
            gamma=row([self.gamma(k) for k in agents], torch.float64),
            horizon=row([self.horizon(k) for k in agents], torch.int64),
        )

    # -- evaluation --------------------------------------------------------------------------

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        """The return and success of θ̃ in each agent's environment (greedy per eval.greedy)."""
        rows = self.begin(round_index, theta, agents)
        horizons = torch.tensor([self.run.eval.horizon or self.horizon(k) for k in agents])
        counts = torch.full((rows.size,), episodes, dtype=torch.int64)
        batch = rows.sample(
            rows.theta,
            counts,
            iteration=0,
            purpose=Purpose.EVALUATE,
            greedy=self.run.eval.greedy,
            horizons=horizons.to(self.device),
        )
        undiscounted = batch.returns().cpu()
        discounted = batch.returns(rows.gammas).cpu()
        lengths = batch.lengths().cpu().double()
        success = batch.success.cpu().double()
        owner = batch.owner.cpu()
        stats = {}
        for a, k in enumerate(rows.agents):
            mine = owner == a
            values = undiscounted[mine]
            stats[k] = EvaluationStats(
                return_mean=float(values.mean()),
                return_std=float(values.std(unbiased=False)),
                discounted_return_mean=float(discounted[mine].mean()),
                success_rate=float(success[mine].mean()),
                length_mean=float(lengths[mine].mean()),
                episodes=episodes,
            )
        return stats
