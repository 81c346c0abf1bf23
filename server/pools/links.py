"""Who is connected: registration, liveness and the replies the server sends on its own.

A :class:`Link` is one registered connection serving a range of logical agents (a lone agent
is a range of one); each of its agents is a :class:`Peer`, selected, answered, dead or rejoined
by index. :class:`Links` keeps them:

- **Registration** (:meth:`Links.admit`): a ``Hello`` is checked (the index range, the
  environment spaces, the digest of the range's variants) and refused with an ``Error`` that
  says why, or welcomed. A range held by a live link is refused as a duplicate; one held by a
  link that no longer answers is taken over (a restarted process, a healed connection).
- **Liveness** (:meth:`Links.keep_alive`, in the order of the zguide's Paranoid Pirate: the
  caller has handled its messages, then dead peers are purged, then heartbeats sent): every
  link gets a heartbeat every ``server.heartbeat_interval_s``; a link silent for
  ``heartbeat_liveness`` intervals, or whose connection is gone, is presumed dead and all its
  agents with it, in one log line (the pool's ``on_lost`` composes it).
- **The connection guard's bookkeeping**: which descriptors belong to registered links, and
  how much a registered link may have queued (a round's answers, twice over).
- **The answer allowance**: every request sent to a link lets it send one more message per
  agent the request names past the loop's per-peer cap (:attr:`Link.allowance`), so that a
  host's answers split one agent per message are never dropped as a flood.

:class:`Outbox` sends without ever blocking the server and answers bad input with an
``Error``: always to a registered link, to a stranger only within a small token bucket, and
its warnings are rate-limited, so a flood gets no flood back.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zmq

from fedhpg.common.configuration.settings.ids import agent_id_of
from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.heterogeneity.variants import range_digest
from fedhpg.common.wire.protocol import (
    KEY_BYTES,
    Error,
    Evaluate,
    Heartbeat,
    Hello,
    MaskRequest,
    Message,
    ShareRequest,
    Train,
    UnmaskRequest,
    Welcome,
)
from fedhpg.common.wire.transport import send_message
from fedhpg.server.connections import ConnectionGuard

logger = logging.getLogger(__name__)

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
    """A registered connection serving the logical agents ``indices``."""

    identity: bytes
    label: str
    """The connection's id: a lone agent's own, or the host's."""
    indices: range
    fd: int = -1
    """The connection's descriptor (``ZMQ_SRCFD``), for the connection guard."""
    last_seen: float = field(default_factory=time.monotonic)
    channel_keys: dict[int, bytes] = field(default_factory=dict)
    """Secure aggregation: each of its agents' channel public key (from its hello)."""
    allowance: int = 0
    """Messages the link may still have handled past the loop's per-peer cap of a turn: one
    per agent named by the requests it was sent (whatever the split, an answer message
    carries one agent's answer at least), banked up to two requests' worth of its agents (an
    answer to the previous request may still be on its way), spent message by message."""

    def allow(self, agents: int) -> None:
        """A request naming ``agents`` of its agents went out: room for their answers."""
        self.allowance = min(self.allowance + agents, 2 * len(self.indices))

    @property
    def host(self) -> bool:
        return len(self.indices) > 1

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


@dataclass(frozen=True)
class Joined:
    """A link just registered: how many of its agents came back, after how long at most."""

    link: Link
    rejoined: int
    away_s: float
    profile: dict


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


def identity_label(identity: bytes) -> str:
    return identity.decode("utf-8", "replace")[:64]


class Outbox:
    """The server's sends on its ROUTER socket (with ZMQ_ROUTER_MANDATORY set)."""

    def __init__(self, socket: zmq.Socket) -> None:
        self.socket = socket
        self.noisy = RateLimitedLog(NOISY_LOG_BURST, NOISY_LOG_WINDOW_S)
        self._replied: dict[bytes, tuple[float, float]] = {}
        self.rejected = 0

    def send(self, identity: bytes, message: Message) -> bool:
        """Send without ever blocking the server; False if the peer cannot be reached."""
        try:
            send_message(self.socket, message, identity=identity, block=False)
            return True
        except zmq.Again:
            self.noisy.warning(
                "%s is not reading its messages (queue full); dropped a %s",
                identity_label(identity),
                type(message).__name__,
            )
        except zmq.ZMQError as error:
            if error.errno != zmq.EHOSTUNREACH:
                logger.warning("could not send to %s: %s", identity_label(identity), error)
        return False

    def routable(self, identity: bytes) -> bool:
        """Whether libzmq still has a connection for ``identity`` (probed by sending a
        heartbeat: with ROUTER_MANDATORY an unknown identity fails at once)."""
        try:
            send_message(self.socket, Heartbeat(), identity=identity, block=False)
        except zmq.Again:
            return True  # connected, only slow
        except zmq.ZMQError:
            return False
        return True

    def reject(self, identity: bytes, code: str, reason: str, *, registered: bool) -> None:
        """Log a refused message and tell its sender why (a stranger within its bucket)."""
        self.rejected += 1
        self.noisy.warning(
            "rejected message from %s: %s: %s", identity_label(identity), code, reason
        )
        if registered or self._may_reply(identity):
            self.send(identity, Error(code=code, reason=reason[:1000]))

    def _may_reply(self, identity: bytes) -> bool:
        """Take a token from the stranger's bucket (REPLY_BURST, refilled at REPLY_RATE/s)."""
        now = time.monotonic()
        tokens, since = self._replied.get(identity, (float(REPLY_BURST), now))
        tokens = min(REPLY_BURST, tokens + (now - since) * REPLY_RATE)
        if len(self._replied) >= REPLY_MEMORY:
            self._replied.clear()
        self._replied[identity] = (tokens - 1.0, now) if tokens >= 1.0 else (tokens, now)
        return tokens >= 1.0


LostHook = Callable[[Link, list[int], str], None]
"""(the dead link, its agents just lost, why) -> None: logs what they leave missing."""


class Links:
    """The registered links and their agents, kept alive or purged."""

    def __init__(
        self,
        *,
        outbox: Outbox,
        num_agents: int,
        env_signature: dict[str, str],
        variant_digests: list[str],
        welcome: Callable[[Link], Welcome],
        settings: ServerConfig,
        answer_bytes: int,
        guard: ConnectionGuard | None = None,
        secure: bool = False,
    ) -> None:
        self.outbox = outbox
        self.secure = secure
        """Secure aggregation: every hello must carry its agents' channel keys."""
        self.num_agents = num_agents
        self.env_signature = env_signature
        self.variant_digests = variant_digests
        self.welcome = welcome
        self.settings = settings
        self.answer_bytes = answer_bytes
        """One agent's answer to a round (θ_k and its statistics), for the guard's allowance."""
        self.guard = guard
        self.liveness_s = settings.heartbeat_interval_s * settings.heartbeat_liveness
        self.by_identity: dict[bytes, Link] = {}
        self.peers: dict[int, Peer] = {}
        self.names: dict[int, str] = {}
        """Agent id per index, kept after an agent dies (metrics still name it)."""
        self.absent_since: dict[int, float] = {}
        self.on_lost: LostHook = lambda link, lost, why: None
        self._last_heartbeat = 0.0
        self.deaths = 0
        self.rejoins = 0

    def name(self, index: int) -> str:
        return self.names.get(index, agent_id_of(index))

    def get(self, identity: bytes) -> Link | None:
        return self.by_identity.get(identity)

    def owns(self, link: Link, index: int) -> bool:
        """Whether agent ``index`` is registered through ``link`` (not lost to another)."""
        peer = self.peers.get(index)
        return peer is not None and peer.link is link

    # -- registration ------------------------------------------------------------------------

    def admit(self, identity: bytes, hello: Hello, fd: int) -> Joined | None:
        """Register the range ``hello`` claims, or refuse it (None: refused, or a resent
        hello answered again)."""
        known = self.by_identity.get(identity)
        if known is not None:  # a resent hello: answer again, idempotently
            self.outbox.send(identity, self.welcome(known))
            return None
        first, count = hello.first, hello.count
        indices = range(first, first + count)
        problem = self._hello_problem(hello, indices)
        if problem is not None:
            self.outbox.reject(identity, *problem, registered=False)
            return None
        holders = {p.link.identity: p.link for k in indices if (p := self.peers.get(k))}
        if len(indices) == 1 and hello.names_agent:  # an id held at another index
            holders |= {
                p.link.identity: p.link for p in self.peers.values() if p.agent_id == hello.id
            }
        for holder in holders.values():
            if self.alive(holder):
                self.outbox.reject(
                    identity,
                    "duplicate_agent",
                    f"{_claim(hello)} is already registered as {holder.describe()}, which is alive",
                    registered=False,
                )
                return None
        for holder in holders.values():
            self.drop(holder, "a new connection claims its place")
        link = Link(identity=identity, label=hello.id, indices=indices, fd=fd)
        if self.secure:
            link.channel_keys = {
                k: bytes(row) for k, row in zip(indices, hello.channel_keys, strict=True)
            }
        names = [hello.id] if hello.names_agent else [agent_id_of(k) for k in indices]
        return self._register(link, names, hello.profile)

    def _hello_problem(self, hello: Hello, indices: range) -> tuple[str, str] | None:
        """(code, reason) of why ``hello`` cannot register, or None."""
        if hello.names_agent and len(indices) != 1:
            return (
                "bad_fields",
                f"{hello.id!r} names its agent by its id, but claims {len(indices)}",
            )
        if self.secure and hello.channel_keys.shape != (len(indices), KEY_BYTES):
            return "unsupported", (
                f"{_claim(hello)} sent no channel keys, and this run aggregates securely "
                "(privacy.mode): the agent program needs pip install 'fedhpg[privacy]'"
            )
        if indices.stop > self.num_agents:
            return "bad_index", (
                f"{_claim(hello)} goes beyond the run's agents 0..{self.num_agents - 1}"
            )
        if hello.env_signature != self.env_signature:
            return "env_signature", (
                f"environment spaces differ from the run's: {hello.id!r} has "
                f"{hello.env_signature}, run has {self.env_signature}"
            )
        expected = range_digest(self.variant_digests[indices.start : indices.stop])
        if hello.variant_digest != expected:
            return "variant_mismatch", (
                f"the environment variants of {_claim(hello)} are not the run's: their digest "
                f"is {hello.variant_digest[:12] or 'missing'}, the run's is {expected[:12]}; "
                "start it with the server's seed and env.* settings"
            )
        return None

    def _register(self, link: Link, agent_ids: list[str], profile: dict) -> Joined:
        if self.guard is not None:
            # a round's answers, twice over (an evaluation's beside them): all it may queue
            allowance = 2 * len(link.indices) * self.answer_bytes
            self.guard.registered(link.fd, True, allowance=allowance)
        self.by_identity[link.identity] = link
        now = time.monotonic()
        rejoined, away_s = 0, 0.0
        for index, agent_id in zip(link.indices, agent_ids, strict=True):
            self.peers[index] = Peer(agent_id=agent_id, index=index, link=link)
            self.names[index] = agent_id
            away = self.absent_since.pop(index, None)
            if away is not None:
                rejoined += 1
                away_s = max(away_s, now - away)
        self.rejoins += rejoined
        self.outbox.send(link.identity, self.welcome(link))
        return Joined(link=link, rejoined=rejoined, away_s=away_s, profile=profile)

    # -- liveness ------------------------------------------------------------------------------

    def alive(self, link: Link) -> bool:
        return (
            self.outbox.routable(link.identity)
            and time.monotonic() - link.last_seen <= self.liveness_s
        )

    def send(self, link: Link, message: Message) -> None:
        """Send to a link; a link whose connection is gone is presumed dead. A request gives
        the link room for its answers past the per-peer cap (:meth:`Link.allow`)."""
        if self.outbox.send(link.identity, message):
            if isinstance(message, Train | Evaluate | ShareRequest | MaskRequest | UnmaskRequest):
                link.allow(len(message.agents))
        elif not self.outbox.routable(link.identity):
            self.drop(link, "its connection is gone")

    def keep_alive(self) -> None:
        """Purge the links quiet for too long, then heartbeat the others when due."""
        now = time.monotonic()
        self.outbox.noisy.flush(now)
        for link in list(self.by_identity.values()):  # per connection, not per logical agent
            silent = now - link.last_seen
            if silent > self.liveness_s:
                self.drop(
                    link,
                    f"silent for {silent:.1f} s (server.heartbeat_liveness × "
                    f"heartbeat_interval_s = {self.liveness_s:g} s)",
                )
        if now - self._last_heartbeat >= self.settings.heartbeat_interval_s:
            self._last_heartbeat = now
            for link in list(self.by_identity.values()):
                self.send(link, Heartbeat())

    def drop(self, link: Link, why: str) -> None:
        """The link's agents are all presumed dead (``on_lost`` says what they leave missing)."""
        if self.by_identity.get(link.identity) is not link:
            return
        del self.by_identity[link.identity]
        if self.guard is not None:
            self.guard.registered(link.fd, False)
        now = time.monotonic()
        lost = []
        for index in link.indices:
            if self.owns(link, index):
                del self.peers[index]
                self.absent_since[index] = now
                self.deaths += 1
                lost.append(index)
        self.on_lost(link, lost, why)


def _claim(hello: Hello) -> str:
    """What a hello claims, in words: ``'agent-3' (index 3)``, ``host 'h' (agents 0..4)``."""
    if hello.count == 1:
        return f"{hello.id!r} (index {hello.first})"
    return f"host {hello.id!r} (agents {hello.first}..{hello.first + hello.count - 1})"
