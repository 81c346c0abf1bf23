"""How the coordinator reaches its agents: an :class:`AgentPool` collects one round's answers.

Two pools: :mod:`.inprocess` (K workers on this thread: tests and sweeps) and :mod:`.zmq_pool`
(agent processes over one ROUTER socket: the product). Both check every update with the same
:class:`~fedhpg.server.validation.UpdateCheck`, so they compute the same θ̃ bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import torch

from fedhpg.common.configuration.settings.ids import agent_id_of
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.records.types import EvaluationStats, RoundResult
from fedhpg.server.validation import Rejection


class FederationError(RuntimeError):
    """The federation cannot go on (agents missing, a round timed out, nothing to aggregate)."""


class SkippedRound(FederationError):
    """A secure round with no sum θ̃ may take (too few keys, inputs or shares; too little
    noise; a weight sum no honest agents can send; a step past ``server.max_update_norm``):
    the coordinator records it and goes on from the θ̃ it had."""

    def __init__(self, round_number: int, reason: str) -> None:
        super().__init__(f"round {round_number}: {reason}")
        self.reason = reason


@dataclass(frozen=True, kw_only=True)
class RoundAnswers:
    """What a pool collected for one round's train request."""

    result: RoundResult
    """The accepted updates (rows in agent-index order; none, when none was accepted)."""
    name: Callable[[int], str] = agent_id_of
    """Each agent's id (its registered one)."""
    failures: dict[str, Rejection] = field(default_factory=dict)
    """Agent id → why its update was rejected (it answered, but is not aggregated)."""
    stragglers: list[str] = field(default_factory=list)
    """Selected agents whose update never arrived in time (late or dead)."""
    secure: SecureSum | None = None
    """Secure aggregation: the round's sum (``result`` then carries statistics, θ̃ as θ)."""


@dataclass(frozen=True, kw_only=True)
class SecureSum:
    """A securely aggregated round's result: the sum of the included agents' contributions
    (float64, d + 2: the weighted updates, the weights, the unclipped count;
    :mod:`fedhpg.common.privacy.contribution`), no one of which the server saw."""

    total: np.ndarray
    inputs: int
    """How many agents' contributions the sum holds."""
    participants: int
    """How many agents took part in the protocol (its n: the noise shares and the fixed point
    are sized from it)."""
    failed: str | None = None
    """Why the round has no sum (too few keys, inputs or shares; too little noise): θ̃ stays
    as it was, the round is recorded as skipped."""


class AgentPool(Protocol):
    """How the coordinator reaches its K agents."""

    @property
    def agent_ids(self) -> list[str]: ...

    def counters(self) -> dict[str, int]:
        """What went wrong so far (rejected messages, deaths, ...), for summary.json and the
        checkpoints."""
        ...

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
        """The local updates of ``round_index`` from θ̃ of the selected agent indices;
        ``private``: aggregate them securely, each agent contributing with these settings;
        ``budgets``: the round's planned budget fields per agent (``agents.plan``);
        ``while_training``: the server's own work, called once, while the agents train where
        they train elsewhere (after the requests went out), else before they train."""
        ...

    def secure_participants(self, agents: Sequence[int]) -> list[int]:
        """The agents of ``agents`` that would take part in a secure round now (registered,
        with a usable channel key): its noise shares are sized from them."""
        ...

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]:
        """Every agent's evaluation of θ̃, keyed by agent id."""
        ...
