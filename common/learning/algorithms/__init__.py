"""Agent-side algorithms by name (``algo.name``): each module of this package is one.

An algorithm is the local half of a federated method: from the server's θ̃ and the agents' own
trajectories it computes each agent's θ_k. It runs on rows: ``rows.theta`` is [A, d], one row
per agent the process trains this round (A = 1 for a lone agent), and every budget field is a
vector ``rows.budget(name)`` [A]. Its ``local_update`` holds the one loop of the method, written
with the round's primitives (:class:`~fedhpg.common.learning.engine.round.Round`: sample,
coefficients, gradients, log-probabilities, bookkeeping), so it runs batched over any number of
agents, on the CPU or a GPU, without a line of its own for that. Adding one is its module here
(or in a plugin) and a YAML in ``conf/algo/``::

    @register_algorithm
    class MyAlgorithm(Algorithm[MyParams, MyBudget]):
        name = "mine"
        Params, Budget = MyParams, MyBudget

        def local_update(self, rows, settings, params) -> torch.Tensor: ...  # θ_k rows [A, d]
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

import torch

from fedhpg.common.configuration.registry import OptionError, Registry
from fedhpg.common.configuration.settings.algo import AlgoConfig

if TYPE_CHECKING:
    from fedhpg.common.learning.engine.round import Round

P = TypeVar("P")
B = TypeVar("B")

PARAMETERS = "parameters"
"""What an agent sends: its θ_k (the paper's algorithms)."""
GRADIENTS = "gradients"
"""What an agent sends: θ̃ + its gradient estimate at θ̃ (FedPG-BR's agents)."""


@dataclass(frozen=True, kw_only=True)
class NoParams:
    """For algorithms without options of their own."""


class Algorithm(abc.ABC, Generic[P, B]):
    """One registered algorithm (a stateless object: every round starts from θ̃)."""

    name: ClassVar[str]
    Params: ClassVar[type[Any]] = NoParams
    """Frozen dataclass of the algorithm's own options (``algo.params``)."""
    Budget: ClassVar[type[Any]]
    """Frozen dataclass of one agent's budget (``agents.budget.<field>[k]``)."""
    strategy: ClassVar[str | None] = None
    """The one server strategy the algorithm's updates mean anything to (None: any)."""
    sends: ClassVar[str] = PARAMETERS
    """What its updates are (:data:`PARAMETERS` or :data:`GRADIENTS`): a strategy takes one."""
    theorem1: ClassVar[bool] = False
    """Whether Theorem 1 (the paper's bound for Algorithm 1's updates) holds for it: then
    ``algo.bound_estimates`` measures its constants and ``agents.plan=theorem1`` plans its
    budgets."""

    @abc.abstractmethod
    def local_update(self, rows: Round, settings: AlgoConfig, params: P) -> torch.Tensor:
        """θ_k of every row from θ̃ (``rows.theta``), [A, d], under the run's ``settings``
        (``algo``); statistics go to the round (:meth:`Round.finished` after each iteration,
        :meth:`Round.report`)."""

    def check(self, settings: AlgoConfig, params: P) -> None:
        """Raise :class:`~fedhpg.common.configuration.registry.OptionError` for options that do not
        go with the run's settings (each option alone is already checked by ``Params``)."""

    def held_trajectories(self, budget: B) -> int:
        """The most trajectories one agent's update holds at once: what the engine plans its
        device memory for (``common/learning/engine/memory.py``). By default the sum of the budget's
        counts, a bound for any loop over them; an algorithm that knows better says so."""
        return sum(v for v in vars(budget).values() if isinstance(v, int))

    def describe_budget(self, budget: B) -> str:
        """A short label of a budget for tables: 'B=8 τ=2'."""
        return " ".join(f"{name}={value}" for name, value in vars(budget).items())


ALGORITHMS: Registry[Algorithm[Any, Any]] = Registry("algorithm", "algo.name", __name__)

A = TypeVar("A", bound=type[Algorithm[Any, Any]])


def register_algorithm(cls: A) -> A:
    """Class decorator: register one instance of ``cls`` under ``cls.name``."""
    ALGORITHMS.register(cls.name)(cls())
    return cls


def at_least_one(name: str, value: int) -> None:
    """For budgets' ``__post_init__``: a count of trajectories or steps must be ≥ 1."""
    if value < 1:
        raise OptionError(name, f"got {value!r}, must be an integer >= 1")
