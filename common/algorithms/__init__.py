"""Agent-side algorithms by name (``algo.name``): each module of this package is one.

An algorithm is the local half of a federated method: from the server's θ̃ and the agent's own
trajectories it computes θ_k. It declares its own options (``Params``, from ``algo.params``)
and its per-agent compute budget (``Budget``, one entry of every ``agents.budget`` list), so
adding one is its module here (or in a plugin) and a YAML in ``conf/algo/``::

    @register_algorithm
    class MyAlgorithm(Algorithm[MyParams, MyBudget]):
        name = "mine"
        Params, Budget = MyParams, MyBudget

        def local_update(self, theta, context, params, budget) -> LocalResult: ...
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar

import torch

from fedhpg.common.config import AlgoConfig
from fedhpg.common.local import IterationHook, TrajectorySource
from fedhpg.common.policies import Policy
from fedhpg.common.registry import OptionError, Registry
from fedhpg.common.types import LocalResult

P = TypeVar("P")
B = TypeVar("B")


@dataclass(frozen=True, kw_only=True)
class NoParams:
    """For algorithms without options of their own."""


@dataclass(frozen=True, kw_only=True)
class LocalContext:
    """What an agent gives its algorithm each round."""

    policy: Policy
    """The agent's policy network; the update loads θ̃ into it and steps it."""
    sample: TrajectorySource
    """n -> n fresh trajectories from the agent's environment at the policy's current θ."""
    settings: AlgoConfig
    """The run's local policy-gradient settings (estimator, baseline, step size, ...)."""
    gamma: float
    """The agent's discount γ_k."""
    on_iteration: IterationHook | None = None
    """Called after every iteration with its compute time and env steps (device emulation,
    cancellation)."""
    seed: int = 0
    """The run's seed: with ``round_index``, what a schedule every agent and the server must
    agree on is drawn from (FedPG-BR's B_t)."""
    round_index: int = 0
    """The round this update belongs to (rounds count from 1)."""


class Algorithm(abc.ABC, Generic[P, B]):
    """One registered algorithm (a stateless object: every round starts from θ̃)."""

    name: ClassVar[str]
    Params: ClassVar[type[Any]] = NoParams
    """Frozen dataclass of the algorithm's own options (``algo.params``)."""
    Budget: ClassVar[type[Any]]
    """Frozen dataclass of one agent's budget (``agents.budget.<field>[k]``)."""
    strategy: ClassVar[str | None] = None
    """The one server strategy the algorithm's updates mean anything to (None: any)."""

    @abc.abstractmethod
    def local_update(
        self, theta: torch.Tensor, context: LocalContext, params: P, budget: B
    ) -> LocalResult:
        """θ_k from θ̃ for one agent and round."""

    def check(self, settings: AlgoConfig, params: P) -> None:
        """Raise :class:`~fedhpg.common.registry.OptionError` for options that do not go with
        the run's settings (each option alone is already checked by ``Params``)."""

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
