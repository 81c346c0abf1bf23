"""The server side of the wire: registration, liveness, request/response rounds, bad input.

:class:`ZmqAgentPool` is the coordinator's :class:`~fedhpg.server.pools.AgentPool` over
one ROUTER socket. One loop (:meth:`ZmqAgentPool._pump`) handles every incoming message,
whatever state the run is in, then keeps the peers alive, in the order of the zguide's
Paranoid Pirate: handle messages, purge dead peers, send heartbeats.

- Bad input (malformed frames, unknown types, wrong versions, bad shapes, dtypes, non-finite
  or too-large updates, duplicate ids, space or variant mismatches) is logged and answered
  with an ``Error``; the run goes on. Updates pass the same
  :class:`~fedhpg.server.validation.UpdateCheck` as in the in-process pool.
- Liveness: every registered agent gets a heartbeat every ``server.heartbeat_interval_s``; an
  agent silent for ``heartbeat_liveness`` intervals, or one its connection is gone for, is
  presumed dead and unregistered. It may register again at any time (a restarted process, a
  healed link) and is then sent the request still open for it, with the current θ̃.
- Round policies (:mod:`fedhpg.server.rounds`) decide when a request's answers are complete;
  late answers for a closed round are discarded with a log line.
- Agent hosts: one connection (a :class:`Link`) may serve a range of logical agents. Each
  agent is still a :class:`Peer` (selected, answered, dead or rejoined by index), but
  registration, liveness, heartbeats and requests go per link: a host registers its range in
  one ``HostHello``, gets one ``TrainBatch`` per round and answers in ``UpdateBatch`` es whose
  rows pass the :class:`UpdateCheck` (each pass over a batch's [A, d] matrix made once for
  all its rows; a bad row rejects that agent only); a dead host's agents all die at once, in
  one log line, and rejoin together when it registers again.
- Buffered rounds (``server.round_policy=buffered``, :mod:`fedhpg.server.buffered_zmq`):
  instead of one round's request, each lone agent has its own open ``Train``
  (:class:`OpenTrain`: its own round index, the θ̃ version it starts from); answers pass the
  same update check against the θ̃ that agent was sent and queue up in arrival order
  (:meth:`ZmqAgentPool.next_arrival`). A dead agent's request is dropped; when it rejoins it
  is sent the newest θ̃ under the same round index. Hosts are refused (one TrainBatch per
  host cannot carry requests of different rounds).
- Accepted θ_k are copied once, on arrival, into the round's
  :class:`~fedhpg.server.round_rows.RoundRows` (the frames are then let go); the updates the
  round returns are views of that matrix, which the strategies use without restacking.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import zmq

from fedhpg.common.config import ServerConfig, agent_id_of
from fedhpg.common.runtime import timeline
from fedhpg.common.types import AgentUpdate, EvaluationStats, UpdateStats
from fedhpg.common.variants import range_digest
from fedhpg.common.wire.codec import ProtocolError
from fedhpg.common.wire.protocol import (
    Error,
    Evaluate,
    EvaluateBatch,
    Evaluation,
    EvaluationBatch,
    Heartbeat,
    Hello,
    HostHello,
    HostWelcome,
    Message,
    Shutdown,
    Train,
    TrainBatch,
    Update,
    UpdateBatch,
    Welcome,
)
from fedhpg.common.wire.security import KEY_MISMATCH, key_mismatch
from fedhpg.common.wire.transport import send_message, try_decode
from fedhpg.server.connections import ConnectionGuard
from fedhpg.server.pools import FederationError, RoundAnswers
from fedhpg.server.round_rows import RoundRows
from fedhpg.server.rounds import request_complete
from fedhpg.server.validation import UpdateCheck

logger = logging.getLogger(__name__)

POLL_INTERVAL_S = 0.2
"""Longest wait on the socket: deadlines and liveness are checked at least this often."""
TURN_MESSAGES = 512
TURN_S = 0.05
"""One turn of the loop handles at most this many messages, or this long, before it purges,
heartbeats and checks the round: a flooding peer cannot starve the others."""
PEER_TURN_MESSAGES = 64
"""Messages of one identity handled per turn; the rest of its turn is dropped unread (libzmq
fair-queues peers, so the others' messages still come through)."""
ANSWER_OVERHEAD_BYTES = 4096
"""An agent's answer beside its θ_k (statistics, framing), generously: the connection guard's
allowance for a registered peer's queued answers."""
REPLY_BURST = 32
REPLY_RATE = 10.0
"""Error replies to an unregistered peer: a bucket of this many, refilled at this rate per
second (a flood gets no flood back; a confused client still hears why)."""
REPLY_MEMORY = 4096
NOISY_LOG_BURST = 20
"""Warnings about peers' messages logged one by one per window; beyond that only counted (a
flood of junk must not turn into a flood of log lines)."""
NOISY_LOG_WINDOW_S = 10.0


@dataclass(eq=False)
class Link:
    """A registered connection: one agent process, or an agent host serving ``indices``."""

    identity: bytes
    label: str
    """The agent id, or the host id."""
    indices: range
    host: bool
    fd: int = -1
    """The connection's descriptor (``ZMQ_SRCFD``), for the connection guard."""
    last_seen: float = field(default_factory=time.monotonic)

    def describe(self) -> str:
        if not self.host:
            return self.label
        return f"host {self.label} (agents {self.indices.start}..{self.indices.stop - 1})"


@dataclass(eq=False)
class Peer:
    """A registered logical agent, reached through its link."""

    agent_id: str
    index: int
    link: Link
    profile: dict[str, Any]

    @property
    def identity(self) -> bytes:
        return self.link.identity


@dataclass
class Collection:
    """One request sent to the selected agents (a round's Train, or an Evaluate) and its answers."""

    request: Train | Evaluate
    expected: frozenset[int]
    """The agents asked (the strategy's selection; every agent for an evaluation)."""
    started: float = field(default_factory=time.monotonic)
    answers: dict[int, AgentUpdate | Evaluation] = field(default_factory=dict)
    failures: dict[int, str] = field(default_factory=dict)
    """Agents whose answer was rejected (it counts as their answer: they are not waited for)."""
    rows: RoundRows | None = None
    """A round's accepted θ_k (None for an evaluation): ``answers`` hold views of its rows."""
    budgets: Mapping[int, Mapping[str, int]] = field(default_factory=dict)
    """A round's planned budgets (``agents.plan``), by agent index; empty: their own."""

    @property
    def round(self) -> int:
        return self.request.round

    def answered(self, index: int) -> bool:
        return index in self.answers or index in self.failures

    def awaits(self, index: int) -> bool:
        """Whether agent ``index`` was asked and has not answered."""
        return index in self.expected and not self.answered(index)


@dataclass
class OpenTrain:
    """Buffered rounds: one agent's own request, open until it answers."""

    request: Train
    version: int
    """The θ̃ version ``request.theta`` is."""
    sent: bool = False
    """False while the agent is dead (or an evaluation is open): sent when it can be."""


@dataclass
class Arrival:
    """Buffered rounds: one agent's answer to its :class:`OpenTrain`, in arrival order."""

    index: int
    round: int
    """The agent's round index the update used (its n-th update: round n's streams)."""
    version: int
    base: np.ndarray
    """The θ̃ it started from."""
    update: AgentUpdate
    problem: str | None
    """Why the update check rejected it (None: accepted)."""


class RateLimitedLog:
    """Logs the first few warnings of each window, then counts the rest and reports the count."""

    def __init__(self, burst: int, window_s: float) -> None:
        self.burst, self.window_s = burst, window_s
        self._window_start = float("-inf")
        self._logged = 0
        self._suppressed = 0

    def flush(self, now: float | None = None) -> None:
        """Report the suppressed count once its window is over (also when the flood ended)."""
        now = time.monotonic() if now is None else now
        if self._suppressed and now - self._window_start >= self.window_s:
            logger.warning(
                "%d more warnings about peers' messages in the last %.0f s (not logged)",
                self._suppressed,
                min(now - self._window_start, 1e9),
            )
            self._suppressed = 0

    def warning(self, message: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._window_start >= self.window_s:
            self.flush(now)
            self._window_start, self._logged, self._suppressed = now, 0, 0
        if self._logged < self.burst:
            self._logged += 1
            logger.warning(message, *args)
        else:
            self._suppressed += 1


def _source_fd(frame: zmq.Frame) -> int:
    """The descriptor of the connection a message came on (-1 where libzmq has none)."""
    try:
        return int(frame.get(zmq.SRCFD))
    except (zmq.ZMQError, TypeError, ValueError):
        return -1


def _identity_label(identity: bytes) -> str:
    return identity.decode("utf-8", "replace")[:64]


class ZmqAgentPool:
    """K agents reached through one bound ROUTER socket (with ZMQ_ROUTER_MANDATORY set)."""

    def __init__(
        self,
        *,
        socket: zmq.Socket,
        num_agents: int,
        check: UpdateCheck,
        env_signature: dict[str, str],
        variant_digests: list[str],
        run_settings: dict[str, Any],
        run_id: str,
        max_bytes: int,
        settings: ServerConfig,
        guard: ConnectionGuard | None = None,
    ) -> None:
        self.socket = socket
        self.num_agents = num_agents
        self.check = check
        self.env_signature = env_signature
        self.variant_digests = variant_digests
        self.run_settings = run_settings
        self.run_id = run_id
        self.max_bytes = max_bytes
        self.settings = settings
        self.guard = guard
        self._replied: dict[bytes, tuple[float, float]] = {}
        self.dropped = 0
        """Messages of flooding peers dropped unread."""
        self.liveness_s = settings.heartbeat_interval_s * settings.heartbeat_liveness
        self.peers: dict[int, Peer] = {}
        self._links: dict[bytes, Link] = {}
        self._names: dict[int, str] = {}
        """Agent id per index, kept after an agent dies (metrics still name it)."""
        self._absent_since: dict[int, float] = {}
        self._collection: Collection | None = None
        self._buffered = settings.round_policy == "buffered"
        self._trains: dict[int, OpenTrain] = {}
        self._arrivals: deque[Arrival] = deque()
        self._newest: tuple[int, np.ndarray] | None = None
        """Buffered rounds: the newest θ̃ and its version (what a rejoining agent is sent)."""
        self._last_heartbeat = 0.0
        self._noisy = RateLimitedLog(NOISY_LOG_BURST, NOISY_LOG_WINDOW_S)
        self.rejected = 0
        self.late_answers = 0
        self.deaths = 0
        self.rejoins = 0

    @property
    def agent_ids(self) -> list[str]:
        return [self._names[k] for k in sorted(self._names)]

    def _name(self, index: int) -> str:
        return self._names.get(index, f"agent-{index}")

    # -- sending -------------------------------------------------------------------------

    def _send(self, identity: bytes, message: Message) -> bool:
        """Send without ever blocking the server; False if the peer cannot be reached."""
        try:
            send_message(self.socket, message, identity=identity, block=False)
            return True
        except zmq.Again:
            self._noisy.warning(
                "%s is not reading its messages (queue full); dropped a %s",
                _identity_label(identity),
                type(message).__name__,
            )
        except zmq.ZMQError as error:
            if error.errno != zmq.EHOSTUNREACH:
                logger.warning("could not send to %s: %s", _identity_label(identity), error)
        return False

    def _send_to_link(self, link: Link, message: Message) -> None:
        if not self._send(link.identity, message) and not self._routable(link):
            self._on_dead(link, "its connection is gone")

    def _routable(self, link: Link) -> bool:
        """Whether libzmq still has a connection for the link's identity (probed by sending a
        heartbeat: with ROUTER_MANDATORY an unknown identity fails at once)."""
        try:
            send_message(self.socket, Heartbeat(), identity=link.identity, block=False)
        except zmq.Again:
            return True  # connected, only slow
        except zmq.ZMQError:
            return False
        return True

    def _reject(self, identity: bytes, code: str, reason: str) -> None:
        self.rejected += 1
        self._noisy.warning(
            "rejected message from %s: %s: %s", _identity_label(identity), code, reason
        )
        if identity not in self._links and not self._may_reply(identity):
            return
        self._send(identity, Error(code=code, reason=reason[:1000]))

    def _may_reply(self, identity: bytes) -> bool:
        """Take a token from the stranger's bucket (REPLY_BURST, refilled at REPLY_RATE/s)."""
        now = time.monotonic()
        tokens, since = self._replied.get(identity, (float(REPLY_BURST), now))
        tokens = min(REPLY_BURST, tokens + (now - since) * REPLY_RATE)
        if len(self._replied) >= REPLY_MEMORY:
            self._replied.clear()
        self._replied[identity] = (tokens - 1.0, now) if tokens >= 1.0 else (tokens, now)
        return tokens >= 1.0

    # -- the loop --------------------------------------------------------------------------

    def _pump(self, timeout_s: float) -> None:
        """Handle what arrives within ``timeout_s`` (capped), one bounded turn, then purge
        and heartbeat."""
        wait_ms = int(max(min(timeout_s, POLL_INTERVAL_S), 0.0) * 1000)
        guard = self.guard
        if guard is not None:
            guard.waiting(True)
        ready = self.socket.poll(wait_ms)
        if guard is not None:
            guard.waiting(False)
            if not ready:
                guard.drained()
        if ready:
            turn_end = time.monotonic() + TURN_S
            per_peer: dict[bytes, int] = {}
            for _ in range(TURN_MESSAGES):
                try:
                    frames = self.socket.recv_multipart(copy=False, flags=zmq.NOBLOCK)
                except zmq.Again:
                    if guard is not None:
                        guard.drained()
                    break
                identity = frames[0].bytes
                seen = per_peer[identity] = per_peer.get(identity, 0) + 1
                if seen > PEER_TURN_MESSAGES:
                    self.dropped += 1
                    if guard is not None:  # a whole message, though not handled
                        guard.delivered(_source_fd(frames[1]))
                    continue
                self._handle(frames)
                if time.monotonic() >= turn_end:
                    break
        self._keep_alive()

    def _keep_alive(self) -> None:
        now = time.monotonic()
        self._noisy.flush(now)
        for link in list(self._links.values()):  # per connection, not per logical agent
            silent = now - link.last_seen
            if silent > self.liveness_s:
                self._on_dead(
                    link,
                    f"silent for {silent:.1f} s (server.heartbeat_liveness × "
                    f"heartbeat_interval_s = {self.liveness_s:g} s)",
                )
        if now - self._last_heartbeat >= self.settings.heartbeat_interval_s:
            self._last_heartbeat = now
            for link in list(self._links.values()):
                self._send_to_link(link, Heartbeat())

    def _on_dead(self, link: Link, why: str) -> None:
        """The link's agents are all presumed dead (one log line for a whole host)."""
        if self._links.get(link.identity) is not link:
            return
        del self._links[link.identity]
        if self.guard is not None:
            self.guard.registered(link.fd, False)
        now = time.monotonic()
        collection = self._collection
        missing = 0
        for index in link.indices:
            peer = self.peers.get(index)
            if peer is None or peer.link is not link:
                continue
            del self.peers[index]
            self._absent_since[index] = now
            self.deaths += 1
            train = self._trains.get(index)
            if train is not None and train.sent:  # dropped: it is sent anew on rejoining
                train.sent = False
                missing += 1
            if collection is not None and collection.awaits(index):
                missing += 1
        if self._buffered and missing and collection is None:
            suffix = "; its update in flight is dropped"
        elif collection is None or not missing:
            suffix = ""
        elif link.host:
            suffix = f"; {missing} of its answers for round {collection.round} are missing"
        else:
            suffix = f"; its answer for round {collection.round} is missing"
        logger.warning("%s presumed dead: %s%s", link.describe(), why, suffix)

    def _handle(self, frames: list[zmq.Frame]) -> None:
        if len(frames) < 2:
            logger.warning("dropped a message without routing identity")
            return
        identity = bytes(frames[0].buffer)
        fd = _source_fd(frames[1])
        if self.guard is not None:
            self.guard.delivered(fd)
        decoded = try_decode(frames[1:], max_bytes=self.max_bytes)
        if isinstance(decoded, ProtocolError):
            self._reject(identity, decoded.code, str(decoded))
            return
        link = self._links.get(identity)
        # security: with CURVE, a key speaks only as the id and for exactly the agents its
        # allow-list entry names
        claimed: tuple[str, range] | tuple[None, None] = (
            (decoded.agent_id, range(decoded.agent_index, decoded.agent_index + 1))
            if isinstance(decoded, Hello)
            else (decoded.host_id, range(decoded.first, decoded.first + decoded.count))
            if isinstance(decoded, HostHello)
            else (link.label, link.indices)
            if link
            else (None, None)
        )
        if (mismatch := key_mismatch(frames[1], *claimed)) is not None:
            self._reject(identity, KEY_MISMATCH, mismatch)
            return
        if link is not None:
            link.last_seen = time.monotonic()
        peer = self.peers.get(link.indices.start) if link is not None and not link.host else None
        if isinstance(decoded, Hello):
            self._on_hello(identity, decoded, fd)
        elif isinstance(decoded, HostHello):
            self._on_host_hello(identity, decoded, fd)
        elif isinstance(decoded, Update | Evaluation) and link is not None and link.host:
            self._reject(identity, "unexpected_type", "a host answers in batches")
        elif isinstance(decoded, Update):
            self._on_update(identity, peer, decoded)
        elif isinstance(decoded, Evaluation):
            self._on_evaluation(identity, peer, decoded)
        elif isinstance(decoded, UpdateBatch | EvaluationBatch):
            self._on_batch(identity, link, decoded)
        elif isinstance(decoded, Heartbeat):
            if link is None:
                self._reject(identity, "not_registered", "heartbeat from an unregistered peer")
        elif isinstance(decoded, Error):
            self._noisy.warning(
                "agent %s reported %s: %s", _identity_label(identity), decoded.code, decoded.reason
            )
        else:
            self._reject(
                identity, "unexpected_type", f"agents do not send {type(decoded).__name__}"
            )

    # -- registration ------------------------------------------------------------------------

    def _on_hello(self, identity: bytes, hello: Hello, fd: int) -> None:
        known = self._links.get(identity)
        if known is not None:  # a resent hello: answer again, idempotently
            if not known.host:
                self._send(identity, self._welcome(known.indices.start))
            return
        if not 0 <= hello.agent_index < self.num_agents:
            self._reject(
                identity,
                "bad_index",
                f"agent index {hello.agent_index} outside 0..{self.num_agents - 1}",
            )
            return
        if hello.env_signature != self.env_signature:
            self._reject(
                identity,
                "env_signature",
                f"environment spaces differ from the run's: agent has {hello.env_signature}, "
                f"run has {self.env_signature}",
            )
            return
        expected = self.variant_digests[hello.agent_index]
        if hello.variant_digest != expected:
            self._reject(
                identity,
                "variant_mismatch",
                f"the environment variant of {hello.agent_id!r} (index {hello.agent_index}) is "
                f"not the run's: its digest is {hello.variant_digest[:12] or 'missing'}, the run's "
                f"is {expected[:12]}; start it with the server's seed and env.* settings",
            )
            return
        holder = self.peers.get(hello.agent_index) or next(
            (p for p in self.peers.values() if p.agent_id == hello.agent_id), None
        )
        if holder is not None:
            if self._alive(holder.link):
                self._reject(
                    identity,
                    "duplicate_agent",
                    f"agent id {hello.agent_id!r} / index {hello.agent_index} is already "
                    f"registered as {holder.agent_id!r}, which is alive",
                )
                return
            self._on_dead(holder.link, "a new connection claims its place")
        link = Link(
            identity=identity,
            label=hello.agent_id,
            indices=range(hello.agent_index, hello.agent_index + 1),
            host=False,
            fd=fd,
        )
        self._register(link, [hello.agent_id], hello.profile)

    def _alive(self, link: Link) -> bool:
        return self._routable(link) and time.monotonic() - link.last_seen <= self.liveness_s

    def _on_host_hello(self, identity: bytes, hello: HostHello, fd: int) -> None:
        known = self._links.get(identity)
        if known is not None:  # a resent hello: answer again, idempotently
            if known.host:
                self._send(identity, self._host_welcome(known))
            return
        first, count = hello.first, hello.count
        if self._buffered:
            self._reject(
                identity,
                "unsupported",
                "server.round_policy=buffered takes lone agents only, not agent hosts "
                "(agent.count > 1)",
            )
            return
        if first + count > self.num_agents:
            self._reject(
                identity,
                "bad_index",
                f"agents {first}..{first + count - 1} go beyond 0..{self.num_agents - 1}",
            )
            return
        if hello.env_signature != self.env_signature:
            self._reject(
                identity,
                "env_signature",
                f"environment spaces differ from the run's: host has {hello.env_signature}, "
                f"run has {self.env_signature}",
            )
            return
        expected = range_digest(self.variant_digests[first : first + count])
        if hello.variant_digest != expected:
            self._reject(
                identity,
                "variant_mismatch",
                f"the environment variants of host {hello.host_id!r} (agents {first}.."
                f"{first + count - 1}) are not the run's: their digest is "
                f"{hello.variant_digest[:12] or 'missing'}, the run's is {expected[:12]}; "
                "start it with the server's seed and env.* settings",
            )
            return
        indices = range(first, first + count)
        holders = {p.link.identity: p.link for k in indices if (p := self.peers.get(k))}
        for holder in holders.values():
            if self._alive(holder):
                self._reject(
                    identity,
                    "duplicate_agent",
                    f"host {hello.host_id!r} claims agents {first}..{first + count - 1}, but "
                    f"{holder.describe()} holds some of them and is alive",
                )
                return
        for holder in holders.values():
            self._on_dead(holder, "a new connection claims its place")
        link = Link(identity=identity, label=hello.host_id, indices=indices, host=True, fd=fd)
        self._register(link, [agent_id_of(k) for k in indices], hello.profile)

    def _register(self, link: Link, agent_ids: list[str], profile: dict[str, Any]) -> None:
        if self.guard is not None:
            # a round's answers, twice over (an evaluation's beside them): all it may queue
            answers = len(link.indices) * (4 * self.check.num_params + ANSWER_OVERHEAD_BYTES)
            self.guard.registered(link.fd, True, allowance=2 * answers)
        self._links[link.identity] = link
        now = time.monotonic()
        rejoined, away_s = 0, 0.0
        for index, agent_id in zip(link.indices, agent_ids, strict=True):
            self.peers[index] = Peer(agent_id=agent_id, index=index, link=link, profile=profile)
            self._names[index] = agent_id
            away = self._absent_since.pop(index, None)
            if away is not None:
                rejoined += 1
                away_s = max(away_s, now - away)
        self.rejoins += rejoined
        self._send(
            link.identity,
            self._host_welcome(link) if link.host else self._welcome(link.indices.start),
        )
        collection = self._collection
        request = self._request_for(link, collection) if collection is not None else None
        resent = (
            f"; sent it the open round {collection.round} request"
            if request is not None and collection is not None
            else ""
        )
        if not rejoined:
            if link.host:
                logger.info("registered %s (%s)", link.describe(), profile)
            else:
                logger.info("registered %s (index %d, %s)", link.label, link.indices.start, profile)
        elif link.host:
            logger.warning(
                "%s rejoined (%d agents back after up to %.1f s away)%s",
                link.describe(),
                rejoined,
                away_s,
                resent,
            )
        else:
            logger.warning("%s rejoined after %.1f s away%s", link.label, away_s, resent)
        if request is not None:
            self._send_to_link(link, request)
        self._send_trains()

    def _welcome(self, index: int) -> Welcome:
        return Welcome(run_id=self.run_id, agent_index=index, run=self.run_settings)

    def _host_welcome(self, link: Link) -> HostWelcome:
        return HostWelcome(
            run_id=self.run_id,
            first=link.indices.start,
            count=len(link.indices),
            run=self.run_settings,
        )

    def _request_for(
        self, link: Link, collection: Collection, agents: Sequence[int] | None = None
    ) -> Message | None:
        """The collection's request as ``link`` gets it (for a host: a batch naming those of
        ``agents``, by default its agents, still unanswered); None if it owes nothing."""
        candidates = link.indices if agents is None else agents
        owed = [k for k in candidates if collection.awaits(k)]
        if not owed:
            return None
        request = collection.request
        planned = collection.budgets
        if not link.host:
            if isinstance(request, Train) and planned:
                return dataclasses.replace(request, budget=dict(planned.get(owed[0], {})))
            return request
        if isinstance(request, Train):
            budgets = [dict(planned.get(k, {})) for k in owed] if planned else []
            return TrainBatch(
                round=request.round, theta=request.theta, agents=owed, budgets=budgets
            )
        return EvaluateBatch(
            round=request.round, theta=request.theta, episodes=request.episodes, agents=owed
        )

    # -- answers -----------------------------------------------------------------------------

    def _check_update(self, update: Update) -> str | None:
        collection = self._collection
        open_round = collection is not None and collection.round == update.round
        broadcast = collection.request.theta if open_round and collection else None
        # decoded stats are within their bounds: the codec enforced them field by field
        return self.check.problem(update.theta, update.stats, broadcast, stats_bounded=True)

    def _open_for(self, peer: Peer | None, round_index: int, kind: type[Train | Evaluate]) -> bool:
        """Whether an answer for ``round_index`` to a ``kind`` request belongs to the request
        still open for this peer; logs if not."""
        collection = self._collection
        if peer is None:
            return False
        if (
            collection is not None
            and isinstance(collection.request, kind)
            and collection.round == round_index
            and collection.awaits(peer.index)
        ):
            return True
        self.late_answers += 1
        self._noisy.warning(
            "discarded a late %s from %s for round %d (no longer open)",
            "update" if kind is Train else "evaluation",
            peer.agent_id,
            round_index,
        )
        return False

    def _file_updates(
        self,
        round_index: int,
        indices: list[int],
        thetas: np.ndarray,
        rows: list[int],
        stats: list[UpdateStats],
    ) -> None:
        """Accept row ``rows[j]`` of ``thetas`` as agent ``indices[j]``'s update (each one open
        for its agent, :meth:`_open_for`): copied into the round's matrix."""
        collection = self._collection
        assert collection is not None and collection.rows is not None
        views = collection.rows.put(indices, thetas, rows)
        for index, theta, agent_stats in zip(indices, views, stats, strict=True):
            collection.answers[index] = AgentUpdate(
                agent_index=index, agent_id=self._name(index), theta=theta, stats=agent_stats
            )

    def _on_update(self, identity: bytes, peer: Peer | None, update: Update) -> None:
        """A lone agent's answer."""
        if self._buffered:
            self._on_buffered_update(identity, peer, update)
            return
        problem = self._check_update(update)
        if problem is not None:
            self._reject(identity, "bad_update", problem)
            if peer is not None and self._open_for(peer, update.round, Train):
                assert self._collection is not None
                self._collection.failures[peer.index] = problem
            return
        if peer is None:
            self._reject(identity, "not_registered", "update from an unregistered peer")
        elif self._open_for(peer, update.round, Train):
            self._file_updates(update.round, [peer.index], update.theta[None], [0], [update.stats])

    def _on_buffered_update(self, identity: bytes, peer: Peer | None, update: Update) -> None:
        """Buffered rounds: an answer to the agent's own open request joins the arrivals,
        checked against the θ̃ that agent was sent (the same check as synchronous rounds)."""
        if peer is None:
            self._reject(identity, "not_registered", "update from an unregistered peer")
            return
        train = self._trains.get(peer.index)
        if train is None or not train.sent or train.request.round != update.round:
            self.late_answers += 1
            self._noisy.warning(
                "discarded a late update from %s for round %d (no longer open)",
                peer.agent_id,
                update.round,
            )
            return
        base = train.request.theta
        problem = self.check.problem(update.theta, update.stats, base, stats_bounded=True)
        if problem is not None:
            self._reject(identity, "bad_update", problem)
        del self._trains[peer.index]
        # the frame is let go: the arrival keeps its own copy of θ_k
        theta = torch.from_numpy(np.array(update.theta, dtype=base.dtype, copy=True))
        self._arrivals.append(
            Arrival(
                index=peer.index,
                round=update.round,
                version=train.version,
                base=base,
                update=AgentUpdate(
                    agent_index=peer.index,
                    agent_id=peer.agent_id,
                    theta=theta,
                    stats=update.stats,
                ),
                problem=problem,
            )
        )

    def _send_trains(self) -> None:
        """Send every open buffered request not sent yet to its agent, if it is registered,
        with the newest θ̃ (none while an evaluation is open: it would cancel that)."""
        if not self._trains or self._collection is not None or self._newest is None:
            return
        version, theta = self._newest
        for index, train in self._trains.items():
            peer = self.peers.get(index)
            if train.sent or peer is None:
                continue
            if train.version != version:  # it died or waited: it starts from the newest θ̃
                train.request = Train(round=train.request.round, theta=theta)
                train.version = version
            train.sent = True
            self._send_to_link(peer.link, train.request)

    def _on_update_batch(self, identity: bytes, link: Link, batch: UpdateBatch) -> None:
        """A host's updates, row by row as if each had come alone, but checked and copied a
        batch at a time."""
        timeline.mark("server", "batch", batch.round)
        collection = self._collection
        open_round = (
            collection is not None
            and isinstance(collection.request, Train)
            and collection.round == batch.round
        )
        broadcast = collection.request.theta if open_round and collection else None
        # decoded stats are within their bounds: the codec enforced them field by field
        problems = self.check.problems(batch.thetas, batch.stats, broadcast, stats_bounded=True)
        indices: list[int] = []
        rows: list[int] = []
        for i, index in enumerate(batch.agents):
            peer = self.peers.get(index)
            if peer is None or peer.link is not link:
                continue  # an agent this link lost to another (it was presumed dead)
            problem = problems[i]
            if problem is not None:
                self._reject(identity, "bad_update", f"{peer.agent_id}: {problem}")
                if self._open_for(peer, batch.round, Train):
                    assert self._collection is not None
                    self._collection.failures[index] = problem
            elif (open_round and collection is not None and collection.awaits(index)) or (
                self._open_for(peer, batch.round, Train)  # not awaited: logged as late
            ):
                indices.append(index)
                rows.append(i)
        if indices:
            records = batch.stats.records()
            stats = [records[i] for i in rows]
            self._file_updates(batch.round, indices, batch.thetas, rows, stats)

    def _on_evaluation(self, identity: bytes, peer: Peer | None, evaluation: Evaluation) -> None:
        problems = evaluation.stats.problems()
        if problems:
            problem = "evaluation stats: " + "; ".join(problems)
            self._reject(identity, "bad_evaluation", problem)
            if self._open_for(peer, evaluation.round, Evaluate):
                assert self._collection is not None and peer is not None
                self._collection.failures[peer.index] = problem
        elif peer is None:
            self._reject(identity, "not_registered", "evaluation from an unregistered peer")
        elif self._open_for(peer, evaluation.round, Evaluate):
            assert self._collection is not None
            self._collection.answers[peer.index] = evaluation

    def _on_batch(
        self, identity: bytes, link: Link | None, batch: UpdateBatch | EvaluationBatch
    ) -> None:
        """A host's answers: each row checked and filed for its own agent, as if it had come
        alone; rows the message cannot vouch for (agents outside the host's range, a shape
        that does not match) are refused without touching the others."""
        if link is None:
            self._reject(identity, "not_registered", "answers from an unregistered peer")
            return
        if not link.host:
            self._reject(identity, "unexpected_type", "a lone agent does not answer in batches")
            return
        rows = len(batch.agents)
        if len(batch.stats) != rows or (
            isinstance(batch, UpdateBatch)
            and (batch.thetas.ndim != 2 or batch.thetas.shape[0] != rows)
        ):
            self._reject(
                identity,
                "bad_update",
                f"{type(batch).__name__}: {rows} agents, {len(batch.stats)} stats"
                + (
                    f", thetas of shape {batch.thetas.shape}"
                    if isinstance(batch, UpdateBatch)
                    else ""
                ),
            )
            return
        outside = [k for k in batch.agents if k not in link.indices]
        if outside or len(set(batch.agents)) != rows:
            self._reject(
                identity,
                "bad_index",
                f"{link.describe()} answered for agents outside its range or twice: "
                f"{outside[:8] or 'a repeated index'}",
            )
            return
        if isinstance(batch, UpdateBatch):
            self._on_update_batch(identity, link, batch)
            return
        for i, index in enumerate(batch.agents):
            peer = self.peers.get(index)
            if peer is None or peer.link is not link:
                continue  # an agent this link lost to another (it was presumed dead)
            self._on_evaluation(identity, peer, Evaluation(round=batch.round, stats=batch.stats[i]))

    # -- collecting a request's answers --------------------------------------------------------

    def _collect(
        self,
        request: Train | Evaluate,
        what: str,
        agents: Sequence[int],
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        while_waiting: Callable[[], None] | None = None,
    ) -> Collection:
        """Send ``request`` to the selected agents and gather answers as the round policy says:
        one message per link (a host's names its selected agents); ``while_waiting`` is called
        once the requests are out, before any answer is read."""
        expected = frozenset(agents)
        rows = RoundRows(expected, self.check.num_params) if isinstance(request, Train) else None
        collection = Collection(
            request=request, expected=expected, rows=rows, budgets=budgets or {}
        )
        self._collection = collection
        by_link: dict[bytes, tuple[Link, list[int]]] = {}
        for index in sorted(collection.expected):
            peer = self.peers.get(index)
            if peer is not None:
                by_link.setdefault(peer.identity, (peer.link, []))[1].append(index)
        for link, selected in by_link.values():
            message = self._request_for(link, collection, selected)
            if message is not None:
                self._send_to_link(link, message)
        is_train = isinstance(request, Train)  # the marks' names: nothing formatted per round
        timeline.mark("server", "train-sent" if is_train else "evaluate-sent", request.round)
        try:
            if while_waiting is not None:
                while_waiting()
            while not self._complete(collection, what):
                self._pump(POLL_INTERVAL_S)
        finally:
            self._collection = None
        timeline.mark(
            "server", "train-collected" if is_train else "evaluate-collected", request.round
        )
        return collection

    def _complete(self, collection: Collection, what: str) -> bool:
        now = time.monotonic()
        return request_complete(
            settings=self.settings,
            what=f"{what} {collection.round}",
            expected=collection.expected,
            answered=collection.answers.keys() | collection.failures.keys(),
            accepted=len(collection.answers),
            live=self.peers.keys(),
            absent_since=self._absent_since,
            elapsed_s=now - collection.started,
            now=now,
            name=self._name,
        )

    # -- the pool interface ----------------------------------------------------------------

    def wait_for_agents(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.peers) < self.num_agents:
            if time.monotonic() >= deadline:
                missing = [k for k in range(self.num_agents) if k not in self.peers]
                raise FederationError(
                    f"only {len(self.peers)} of {self.num_agents} agents registered within "
                    f"{timeout_s:g} s (server.register_timeout_s); missing agent indices "
                    f"{missing} (default ids: {', '.join(f'agent-{k}' for k in missing)})"
                )
            self._pump(deadline - time.monotonic())

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        while_training: Callable[[], None] | None = None,
    ) -> RoundAnswers:
        request = Train(round=round_index, theta=theta.detach().numpy())
        collection = self._collect(request, "round", agents, budgets, while_training)
        stragglers = [
            self._name(k) for k in sorted(collection.expected) if not collection.answered(k)
        ]
        if stragglers:
            logger.warning(
                "round %d aggregated %d of %d updates; stragglers: %s",
                round_index,
                len(collection.answers),
                len(collection.expected),
                ", ".join(stragglers),
            )
        accepted = [
            update
            for _, update in sorted(collection.answers.items())
            if isinstance(update, AgentUpdate)
        ]
        assert collection.rows is not None
        return RoundAnswers(
            # views of one [K, d] matrix: strategies.stacked hands it on as it is
            updates=collection.rows.compacted(accepted),
            failures={self._name(k): r for k, r in sorted(collection.failures.items())},
            stragglers=stragglers,
        )

    # -- buffered rounds (server/buffered_zmq.py) ---------------------------------------------

    def start_trains(
        self, requests: Sequence[tuple[int, int]], version: int, theta: torch.Tensor
    ) -> None:
        """Open a request for each (agent index, its round index) from θ̃ (``version``, the
        newest) and send those whose agent is registered; the others get it on rejoining."""
        broadcast = theta.detach().numpy()
        self._newest = (version, broadcast)
        for index, round_index in requests:
            self._trains[index] = OpenTrain(
                request=Train(round=round_index, theta=broadcast), version=version
            )
        self._send_trains()

    def _stalled(self, since: float) -> None:
        """Raise FederationError when no arrival can come any more."""
        now = time.monotonic()
        if now - since > self.settings.round_timeout_s:
            open_for = [self._name(k) for k in sorted(self._trains)]
            raise FederationError(
                f"timed out after {self.settings.round_timeout_s:g} s "
                f"(server.round_timeout_s) waiting for an update from {open_for}"
            )
        if any(k in self.peers for k in self._trains):
            return
        gone = [k for k in self._trains if k in self._absent_since]
        if gone and all(now - self._absent_since[k] > self.settings.rejoin_timeout_s for k in gone):
            raise FederationError(
                f"every agent still owing an update ({[self._name(k) for k in sorted(gone)]}) "
                f"died and did not rejoin within {self.settings.rejoin_timeout_s:g} s "
                "(server.rejoin_timeout_s)"
            )

    def outstanding(self) -> int:
        """Buffered rounds: updates that may still arrive (open requests, queued arrivals)."""
        return len(self._trains) + len(self._arrivals)

    def next_arrival(self) -> Arrival:
        """The next answer in arrival order (waiting for one)."""
        since = time.monotonic()
        while not self._arrivals:
            self._stalled(since)
            self._pump(POLL_INTERVAL_S)
        return self._arrivals.popleft()

    def drain(self) -> None:
        """Wait until no registered agent is training (their answers queue up as arrivals):
        evaluation pauses dispatch rather than cancel work in flight."""
        since = time.monotonic()
        while any(k in self.peers and t.sent for k, t in self._trains.items()):
            self._stalled(since)
            self._pump(POLL_INTERVAL_S)

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]:
        request = Evaluate(round=round_index, theta=theta.detach().numpy(), episodes=episodes)
        collection = self._collect(request, "evaluation of round", range(self.num_agents))
        self._send_trains()  # an agent that rejoined during the evaluation
        return {
            self._name(k): answer.stats
            for k, answer in sorted(collection.answers.items())
            if isinstance(answer, Evaluation)
        }

    def counters(self) -> dict[str, int]:
        """What went wrong so far, for summary.json (kept across resumes by the checkpoints)."""
        return {
            "rejected_messages": self.rejected,
            "late_answers": self.late_answers,
            "agent_deaths": self.deaths,
            "agent_rejoins": self.rejoins,
            "dropped_flood_messages": self.dropped,
        }

    def restore_counters(self, counters: dict[str, int]) -> None:
        self.rejected = counters.get("rejected_messages", 0)
        self.late_answers = counters.get("late_answers", 0)
        self.deaths = counters.get("agent_deaths", 0)
        self.rejoins = counters.get("agent_rejoins", 0)
        self.dropped = counters.get("dropped_flood_messages", 0)

    def shutdown(self, reason: str, *, complete: bool = True) -> None:
        """Tell every agent the run is over (``complete``) or was aborted."""
        message = Shutdown(reason=reason[:1000], complete=complete)
        for link in self._links.values():
            self._send(link.identity, message)
