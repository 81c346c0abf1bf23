"""A secure round's two sides without sockets: the server's exchange (server/pools/secure.py)
against lone agents' sides (agent/work.py's ``SecureAgents``), every message through the codec
both ways, as over ZeroMQ. A rogue participant is an honest side whose answers a script
rewrites (or replaces with raw frames the codec would refuse to send).

- :class:`Wire`: stands in for the server's ``Collector``: sends each agent its request, files
  the answers row by row for the agents they name (as ``Collector.on_secure`` does), drops what
  the codec refuses and answers for agents a side does not serve (as the pool does).
- :class:`HonestSide`: agent k's own side; its round's update is a fixed step from θ̃.
- :func:`secure_round`: one round among K sides, its answers and the honest mean.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from fedhpg.agent.work import SecureAgents
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.records.types import RoundResult, UpdateColumns, UpdateStats
from fedhpg.common.wire.codec import ProtocolError, decode, encode
from fedhpg.common.wire.protocol import (
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    Message,
    ShareRequest,
    Train,
    Unmasking,
    UnmaskRequest,
)
from fedhpg.server.pools import RoundAnswers
from fedhpg.server.pools.secure import SecureExchange

MAX_BYTES = 64 << 20
ANSWER_TO = {
    Train: MaskKeys,
    ShareRequest: KeyShares,
    MaskRequest: MaskedUpdate,
    UnmaskRequest: Unmasking,
}
Reply = Message | list[bytes]


def step_of(k: int, num_params: int) -> np.ndarray:
    """Agent k's round update θ_k − θ̃ (float32; within any clip of 1)."""
    return (np.random.default_rng(k).standard_normal(num_params) * 0.01).astype(np.float32)


def stats_of(k: int) -> UpdateStats:
    return UpdateStats(trajectories=3 + k, env_steps=30, compute_s=0.1, train_return=0.0)


class HonestSide:
    """Agent k as its program would answer each of the round's requests."""

    def __init__(self, run: RunConfig, k: int) -> None:
        self.k = k
        self.agents = SecureAgents(run, f"agent-{k}")
        self.channel_key = self.agents.keys.agent(k).channel_public

    def answer(self, request: Message) -> list[Reply]:
        if isinstance(request, Train):
            theta = torch.from_numpy(np.array(request.theta))
            result = RoundResult(
                round=request.round,
                agents=[self.k],
                thetas=(theta.numpy() + step_of(self.k, theta.numel()))[None],
                stats=UpdateColumns.of([stats_of(self.k)]),
            )
            return list(self.agents.share(request, theta, result, MAX_BYTES))
        if isinstance(request, ShareRequest):
            return list(self.agents.share_keys(request, MAX_BYTES))
        if isinstance(request, MaskRequest):
            return list(self.agents.mask(request, MAX_BYTES))
        assert isinstance(request, UnmaskRequest)
        return list(self.agents.reveal(request, MAX_BYTES))


class RogueSide(HonestSide):
    """Agent k, registered as any other, whose answers ``script(request, honest answers)``
    rewrites."""

    def __init__(
        self, run: RunConfig, k: int, script: Callable[[Message, list[Reply]], list[Reply]]
    ) -> None:
        super().__init__(run, k)
        self.script = script

    def answer(self, request: Message) -> list[Reply]:
        return self.script(request, super().answer(request))


class Wire:
    """The server's collector, with each side reached through the codec."""

    def __init__(self, sides: Mapping[int, HonestSide]) -> None:
        self.sides = sides
        self.refused = 0
        """Answers the codec refused (the pool would reject them, as any bad frame)."""

    def collect(
        self,
        request: Any,
        what: str,
        agents: Sequence[int],
        *,
        pump: Callable[[], None],
        budgets: Any = None,
        while_waiting: Callable[[], None] | None = None,
        rows_for: Callable[[list[int]], Any] | None = None,
        phase: bool = False,
    ) -> SimpleNamespace:
        if while_waiting is not None:
            while_waiting()
        expected = set(agents)
        answers: dict[int, tuple[Message, int]] = {}
        for k in sorted(expected):
            side = self.sides.get(k)
            if side is None:
                continue
            sent = rows_for([k]) if rows_for else dataclasses.replace(request, agents=[k])
            for reply in side.answer(decode(encode(sent))):
                try:
                    message = decode(reply if isinstance(reply, list) else encode(reply))
                except ProtocolError:
                    self.refused += 1
                    continue
                if (
                    type(message) is not ANSWER_TO[type(request)]
                    or message.round != request.round  # type: ignore[union-attr]
                    or any(i != k for i in message.agents)  # type: ignore[union-attr]
                ):
                    continue
                for row, index in enumerate(message.agents):  # type: ignore[union-attr]
                    if index in expected and index not in answers:
                        answers[index] = (message, row)
        return SimpleNamespace(answers=answers)


class Links:
    """The registered agents and their channel keys, as the pool's links hold them."""

    def __init__(self, keys: Mapping[int, bytes]) -> None:
        self.peers = {
            k: SimpleNamespace(link=SimpleNamespace(channel_keys={k: key}))
            for k, key in keys.items()
        }

    @staticmethod
    def name(k: int) -> str:
        return f"agent-{k}"


def secure_round(
    run: RunConfig,
    sides: Mapping[int, HonestSide],
    *,
    num_params: int = 6,
    round_index: int = 1,
    private: RoundPrivacy | None = None,
    keys: Mapping[int, bytes] | None = None,
    theta: torch.Tensor | None = None,
    agents: Sequence[int] | None = None,
) -> RoundAnswers:
    """One secure round of ``agents`` (default: every side's agent) from θ̃ (default 0)."""
    theta = torch.zeros(num_params) if theta is None else theta
    exchange = SecureExchange(run, theta.numel())
    links = Links(keys if keys is not None else {k: s.channel_key for k, s in sides.items()})
    return exchange.round(
        Wire(sides),  # type: ignore[arg-type]
        links,  # type: ignore[arg-type]
        lambda: None,
        round_index,
        theta,
        sorted(sides) if agents is None else sorted(agents),
        private or RoundPrivacy(bound=1.0e4),
    )


class SecurePool:
    """The coordinator's pool over these sides: its agents ``sides`` are registered, any other
    selected agent is not (it takes no part, as over ZeroMQ); ``sent`` keeps each round's
    ``private`` settings."""

    def __init__(self, run: RunConfig, sides: Mapping[int, HonestSide]) -> None:
        self.run = run
        self.sides = sides
        self.sent: list[RoundPrivacy | None] = []

    @property
    def agent_ids(self) -> list[str]:
        return [f"agent-{k}" for k in range(self.run.agents.num_agents)]

    def secure_participants(self, agents: Sequence[int]) -> list[int]:
        return sorted(k for k in agents if k in self.sides)

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Any = None,
        while_training: Callable[[], None] | None = None,
        private: RoundPrivacy | None = None,
    ) -> RoundAnswers:
        if while_training is not None:
            while_training()
        self.sent.append(private)
        return secure_round(
            self.run, self.sides, round_index=round_index, private=private, theta=theta,
            agents=agents,
        )  # fmt: skip

    def evaluate(self, round_index: int, theta: torch.Tensor, episodes: int) -> dict:
        return {}

    def counters(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        pass


def honest_mean(ks: Sequence[int], num_params: int = 6) -> np.ndarray:
    """The mean step of agents ``ks`` (what an unweighted secure round must give)."""
    return np.mean([step_of(k, num_params).astype(np.float64) for k in ks], axis=0)
