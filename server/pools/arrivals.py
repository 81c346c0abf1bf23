"""Buffered rounds over the wire: each agent's own request, and its answers in arrival order.

With ``server.round_policy=buffered`` (:mod:`fedhpg.server.buffered_zmq` drives it) there is no
round's request: each agent has its own open ``Train`` (:class:`OpenTrain`: its own round
index, the θ̃ version it starts from). An answer passes the same update check as in
synchronous rounds, against the θ̃ that agent was sent, and queues up as an :class:`Arrival`
in the order it reached the server. A dead agent's request in flight is dropped; when it
rejoins it is sent the newest θ̃ under the same round index. One ``Train`` carries one round
index, so buffered rounds take links of one agent only (:mod:`fedhpg.server.pools.links`
refuses a wider range on a buffered server).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.records.types import UpdateStats
from fedhpg.common.wire.protocol import Train, Update
from fedhpg.server.pools import FederationError
from fedhpg.server.pools.links import Link, Links, Outbox
from fedhpg.server.validation import Rejection, UpdateCheck


@dataclass
class OpenTrain:
    """One agent's own request, open until it answers."""

    request: Train
    version: int
    """The θ̃ version ``request.theta`` is."""
    sent: bool = False
    """False while the agent is dead (or an evaluation is open): sent when it can be."""


@dataclass
class Arrival:
    """One agent's answer to its :class:`OpenTrain`, in arrival order."""

    index: int
    round: int
    """The agent's round index the update used (its n-th update: round n's streams)."""
    version: int
    base: np.ndarray
    """The θ̃ it started from."""
    agent_id: str
    theta: torch.Tensor
    """θ_k (its own copy: the frame it came in is let go)."""
    stats: UpdateStats
    problem: Rejection | None
    """Why the update check rejected it (None: accepted)."""


class Arrivals:
    """The agents' open requests and their answers, queued in arrival order."""

    def __init__(
        self, *, links: Links, outbox: Outbox, check: UpdateCheck, settings: ServerConfig
    ) -> None:
        self.links = links
        self.outbox = outbox
        self.check = check
        self.settings = settings
        self.trains: dict[int, OpenTrain] = {}
        self.queue: deque[Arrival] = deque()
        self.newest: tuple[int, np.ndarray] | None = None
        """The newest θ̃ and its version (what a rejoining agent is sent)."""
        self.late_answers = 0

    def start(self, requests: Sequence[tuple[int, int]], version: int, theta: torch.Tensor) -> None:
        """Open a request for each (agent index, its round index) from θ̃ (``version``, the
        newest); :meth:`send` sends those whose agent is registered."""
        broadcast = theta.detach().numpy()
        self.newest = (version, broadcast)
        for index, round_index in requests:
            request = Train(round=round_index, theta=broadcast, agents=[index])
            self.trains[index] = OpenTrain(request=request, version=version)

    def send(self) -> None:
        """Send every open request not sent yet to its agent, if it is registered, with the
        newest θ̃ (the caller holds this back while an evaluation is open: it would cancel
        that)."""
        if self.newest is None:
            return
        version, theta = self.newest
        for index, train in self.trains.items():
            peer = self.links.peers.get(index)
            if train.sent or peer is None:
                continue
            if train.version != version:  # it died or waited: it starts from the newest θ̃
                train.request = Train(round=train.request.round, theta=theta, agents=[index])
                train.version = version
            train.sent = True
            self.links.send(peer.link, train.request)

    def lost(self, indices: Sequence[int]) -> int:
        """Agents presumed dead: their requests in flight are dropped (sent anew when they
        rejoin); how many were in flight."""
        missing = 0
        for index in indices:
            train = self.trains.get(index)
            if train is not None and train.sent:
                train.sent = False
                missing += 1
        return missing

    def on_update(self, identity: bytes, link: Link, update: Update) -> None:
        """Answers to the agents' own requests join the arrivals, each checked against the θ̃
        that agent was sent (the same check as synchronous rounds)."""
        records = update.stats.records()
        for i, index in enumerate(update.agents):
            if not self.links.owns(link, index):
                continue
            train = self.trains.get(index)
            if train is None or not train.sent or train.request.round != update.round:
                self.late_answers += 1
                self.outbox.noisy.warning(
                    "discarded a late update from %s for round %d (no longer open)",
                    self.links.name(index),
                    update.round,
                )
                continue
            base = train.request.theta
            row, stats = update.thetas[i], records[i]
            problem = self.check.problem(row, stats, base, stats_bounded=True)
            if problem is not None:
                self.outbox.reject(
                    identity, "bad_update", f"{self.links.name(index)}: {problem}", registered=True
                )
            del self.trains[index]
            # the frame is let go: the arrival keeps its own copy of θ_k
            theta = torch.from_numpy(np.array(row, dtype=base.dtype, copy=True))
            self.queue.append(
                Arrival(
                    index=index,
                    round=update.round,
                    version=train.version,
                    base=base,
                    agent_id=self.links.name(index),
                    theta=theta,
                    stats=stats,
                    problem=problem,
                )
            )

    def outstanding(self) -> int:
        """Updates that may still arrive (open requests, queued arrivals)."""
        return len(self.trains) + len(self.queue)

    def training(self) -> bool:
        """Whether a registered agent is training (its request was sent)."""
        return any(k in self.links.peers and t.sent for k, t in self.trains.items())

    def check_stalled(self, since: float) -> None:
        """Raise FederationError when no arrival can come any more."""
        now = time.monotonic()
        name = self.links.name
        if now - since > self.settings.round_timeout_s:
            open_for = [name(k) for k in sorted(self.trains)]
            raise FederationError(
                f"timed out after {self.settings.round_timeout_s:g} s "
                f"(server.round_timeout_s) waiting for an update from {open_for}"
            )
        if any(k in self.links.peers for k in self.trains):
            return
        absent = self.links.absent_since
        gone = [k for k in self.trains if k in absent]
        if gone and all(now - absent[k] > self.settings.rejoin_timeout_s for k in gone):
            raise FederationError(
                f"every agent still owing an update ({[name(k) for k in sorted(gone)]}) "
                f"died and did not rejoin within {self.settings.rejoin_timeout_s:g} s "
                "(server.rejoin_timeout_s)"
            )
