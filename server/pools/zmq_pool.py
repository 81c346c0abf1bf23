"""The server side of the wire: the coordinator's :class:`~fedhpg.server.pools.AgentPool`
over one ROUTER socket.

One loop (:meth:`ZmqAgentPool.pump`) handles every incoming message, whatever state the run is
in, then keeps the peers alive, in the order of the zguide's Paranoid Pirate: handle messages,
purge dead peers, send heartbeats. It only routes; each job is a module of its own:

- :mod:`.links`: registration, liveness, the connection guard's bookkeeping, the replies;
- :mod:`.collection`: a synchronous round's or an evaluation's request and its answers, closed
  by the round policy (:mod:`fedhpg.server.pools.rounds`);
- :mod:`.arrivals`: buffered rounds' per-agent requests and their answers in arrival order.

A turn of the loop handles at most ``PEER_TURN_MESSAGES`` messages of one identity and drops
the rest unread, so that a flooding peer cannot starve the others. A host's answers are exempt:
past the cap, a registered link's messages are still handled while an open request waits for
one of its agents, up to one message per agent it was asked for (:attr:`Link.allowance`: an
answer message carries one agent's answer at least, whatever ``server.max_message_mb`` makes
of the split). Unsolicited answers, duplicates beyond that allowance, heartbeat floods and junk
stay capped.

Bad input (malformed frames, unknown types, wrong versions, bad shapes, dtypes, non-finite or
too-large updates, answers for agents the connection does not serve, duplicate ids, space or
variant mismatches) is logged and answered with an ``Error``; the run goes on. With CURVE, a
key speaks only as the id and for exactly the agents its allow-list entry names.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
import zmq

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.wire.codec import ProtocolError
from fedhpg.common.wire.protocol import (
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    Shutdown,
    Train,
    Unmasking,
    Update,
    Welcome,
)
from fedhpg.common.wire.security import KEY_MISMATCH, key_mismatch
from fedhpg.common.wire.transport import try_decode
from fedhpg.server.connections import ConnectionGuard
from fedhpg.server.pools import FederationError, RoundAnswers
from fedhpg.server.pools.arrivals import Arrival, Arrivals
from fedhpg.server.pools.collection import Collector
from fedhpg.server.pools.links import (
    ANSWER_OVERHEAD_BYTES,
    Joined,
    Link,
    Links,
    Outbox,
    identity_label,
)
from fedhpg.server.pools.secure import SecureExchange
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
fair-queues peers, so the others' messages still come through), except a registered link's
answers to an open request, within its allowance (see the module's docstring)."""


def _source_fd(frame: zmq.Frame) -> int:
    """The descriptor of the connection a message came on (-1 where libzmq has none)."""
    try:
        return int(frame.get(zmq.SRCFD))
    except (zmq.ZMQError, TypeError, ValueError):
        return -1


def index_ranges(indices: Sequence[int], *, shown: int = 8) -> str:
    """Agent indices as ranges, the first ``shown`` of them: "agents 3, 7-9 (4 in all)", a
    line that stays short at any K (a list of 168 missing agents once took 3 KB)."""
    spans: list[tuple[int, int]] = []
    for k in sorted(indices):
        if spans and k == spans[-1][1] + 1:
            spans[-1] = (spans[-1][0], k)
        else:
            spans.append((k, k))
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans[:shown])
    more = ", …" if len(spans) > shown else ""
    return f"agents {text}{more} ({len(indices)} in all)"


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
        secure: SecureExchange | None = None,
    ) -> None:
        self.socket = socket
        self.secure = secure
        """Secure aggregation (``privacy.mode``): the exchanges after a private Train."""
        self.num_agents = num_agents
        self.run_settings = run_settings
        self.run_id = run_id
        self.max_bytes = max_bytes
        self.settings = settings
        self.guard = guard
        self.buffered = ROUND_POLICIES.get(settings.round_policy).asynchronous
        self.outbox = Outbox(socket)
        self.links = Links(
            outbox=self.outbox,
            num_agents=num_agents,
            env_signature=env_signature,
            variant_digests=variant_digests,
            welcome=self._welcome,
            settings=settings,
            answer_bytes=max(4 * check.num_params, secure.answer_bytes if secure is not None else 0)
            + ANSWER_OVERHEAD_BYTES,
            guard=guard,
            secure=secure is not None,
        )
        self.links.on_lost = self._on_lost
        self.collector = Collector(
            links=self.links, outbox=self.outbox, check=check, settings=settings
        )
        self.arrivals = Arrivals(
            links=self.links, outbox=self.outbox, check=check, settings=settings
        )
        self.dropped = 0
        """Messages of flooding peers dropped unread."""

    @property
    def agent_ids(self) -> list[str]:
        names = self.links.names
        return [names[k] for k in sorted(names)]

    # -- the loop ----------------------------------------------------------------------------

    def pump(self, timeout_s: float = POLL_INTERVAL_S) -> None:
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
            owing: dict[bytes, bool] = {}
            for _ in range(TURN_MESSAGES):
                try:
                    frames = self.socket.recv_multipart(copy=False, flags=zmq.NOBLOCK)
                except zmq.Again:
                    if guard is not None:
                        guard.drained()
                    break
                identity = frames[0].bytes
                seen = per_peer[identity] = per_peer.get(identity, 0) + 1
                if seen > PEER_TURN_MESSAGES and not self._past_cap(identity, owing):
                    self.dropped += 1
                    if guard is not None:  # a whole message, though not handled
                        guard.delivered(_source_fd(frames[1]))
                    continue
                self._handle(frames)
                if time.monotonic() >= turn_end:
                    break
        self.links.keep_alive()

    def _past_cap(self, identity: bytes, owing: dict[bytes, bool]) -> bool:
        """Whether a message of ``identity`` past this turn's per-peer cap is handled all the
        same (one of the link's allowance spent): the identity is a registered link and an
        open request still waits for one of its agents (asked once per turn, in ``owing``; a
        link that owes nothing loses what is left of its allowance)."""
        link = self.links.get(identity)
        if link is None:
            return False
        owes = owing.get(identity)
        if owes is None:
            owes = owing[identity] = self._owes(link)
            if not owes:
                link.allowance = 0
        if not owes or link.allowance <= 0:
            return False
        link.allowance -= 1
        return True

    def _owes(self, link: Link) -> bool:
        """Whether an open request (a round's, an evaluation's, a secure exchange's, or a
        buffered round's own) still waits for an answer of one of ``link``'s agents."""
        collection = self.collector.open
        if collection is not None and any(collection.awaits(k) for k in link.indices):
            return True
        trains = self.arrivals.trains
        return any((train := trains.get(k)) is not None and train.sent for k in link.indices)

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
        link = self.links.get(identity)
        # security: with CURVE, a key speaks only as the id and for exactly the agents its
        # allow-list entry names
        claimed: tuple[str, range] | tuple[None, None] = (
            (decoded.id, range(decoded.first, decoded.first + decoded.count))
            if isinstance(decoded, Hello)
            else (link.label, link.indices)
            if link
            else (None, None)
        )
        if (mismatch := key_mismatch(frames[1], *claimed)) is not None:
            self._reject(identity, KEY_MISMATCH, mismatch)
            return
        if link is not None:
            link.last_seen = time.monotonic()
        if isinstance(decoded, Hello):
            self._on_hello(identity, decoded, fd)
        elif isinstance(decoded, Update | Evaluation):
            self._on_answer(identity, link, decoded)
        elif isinstance(decoded, MaskKeys | KeyShares | MaskedUpdate | Unmasking):
            if link is None:
                self._reject(identity, "not_registered", "answers from an unregistered peer")
            elif any(k not in link.indices for k in decoded.agents):
                self._reject(identity, "bad_index", f"{link.describe()} answered for others")
            else:
                self.collector.on_secure(link, decoded)
        elif isinstance(decoded, Heartbeat):
            if link is None:
                self._reject(identity, "not_registered", "heartbeat from an unregistered peer")
        elif isinstance(decoded, Error):
            self.outbox.noisy.warning(
                "agent %s reported %s: %s", identity_label(identity), decoded.code, decoded.reason
            )
        else:
            self._reject(
                identity, "unexpected_type", f"agents do not send {type(decoded).__name__}"
            )

    def _reject(self, identity: bytes, code: str, reason: str) -> None:
        registered = self.links.get(identity) is not None
        self.outbox.reject(identity, code, reason, registered=registered)

    # -- registration and deaths ---------------------------------------------------------------

    def _welcome(self, link: Link) -> Welcome:
        first, count = link.indices.start, len(link.indices)
        return Welcome(run_id=self.run_id, first=first, count=count, run=self.run_settings)

    def _on_hello(self, identity: bytes, hello: Hello, fd: int) -> None:
        if self.buffered and hello.count > 1 and self.links.get(identity) is None:
            self._reject(
                identity,
                "unsupported",
                "server.round_policy=buffered takes lone agents only, not agent hosts "
                "(agent.count > 1): one Train carries one round index",
            )
            return
        joined = self.links.admit(identity, hello, fd)
        if joined is not None:
            self._on_joined(joined)

    def _on_joined(self, joined: Joined) -> None:
        """A registered link: welcomed; sent what the open request still owes it."""
        link = joined.link
        request = self.collector.request_for(link)
        resent = f"; sent it the open round {request.round} request" if request is not None else ""
        if not joined.rejoined:
            if link.host:
                logger.info("registered %s (%s)", link.describe(), joined.profile)
            else:
                start = link.indices.start
                logger.info("registered %s (index %d, %s)", link.label, start, joined.profile)
        elif link.host:
            logger.warning(
                "%s rejoined (%d agents back after up to %.1f s away)%s",
                link.describe(),
                joined.rejoined,
                joined.away_s,
                resent,
            )
        else:
            logger.warning("%s rejoined after %.1f s away%s", link.label, joined.away_s, resent)
        if request is not None:
            self.links.send(link, request)
        self._send_trains()

    def _on_lost(self, link: Link, lost: list[int], why: str) -> None:
        """One log line for a dead link's agents, naming what they leave missing."""
        collection = self.collector.open
        in_flight = self.arrivals.lost(lost)
        missing = in_flight + self.collector.owed_by(lost)
        if self.buffered and missing and collection is None:
            suffix = "; its update in flight is dropped"
        elif collection is None or not missing:
            suffix = ""
        elif link.host:
            suffix = f"; {missing} of its answers for round {collection.round} are missing"
        else:
            suffix = f"; its answer for round {collection.round} is missing"
        logger.warning("%s presumed dead: %s%s", link.describe(), why, suffix)

    # -- answers -------------------------------------------------------------------------------

    def _on_answer(self, identity: bytes, link: Link | None, answer: Update | Evaluation) -> None:
        """An answer's rows, each for its own agent; rows the message cannot vouch for (a
        shape that does not match, agents outside the link's range) refuse the message
        without touching the others."""
        rows = len(answer.agents)
        is_update = isinstance(answer, Update)
        if len(answer.stats) != rows or (
            isinstance(answer, Update)
            and (answer.thetas.ndim != 2 or answer.thetas.shape[0] != rows)
        ):
            self._reject(
                identity,
                "bad_update" if is_update else "bad_evaluation",
                f"{type(answer).__name__}: {rows} agents, {len(answer.stats)} stats"
                + (
                    f", thetas of shape {answer.thetas.shape}" if isinstance(answer, Update) else ""
                ),
            )
            return
        if link is None:
            # a stranger still hears what is wrong with its update before that it is unknown
            problems = (
                self.collector.check.problems(answer.thetas, answer.stats, None, stats_bounded=True)
                if isinstance(answer, Update)
                else []
            )
            found = next((p for p in problems if p is not None), None)
            if found is not None:
                self._reject(identity, "bad_update", str(found))
            else:
                self._reject(identity, "not_registered", "answers from an unregistered peer")
            return
        outside = [k for k in answer.agents if k not in link.indices]
        if outside or len(set(answer.agents)) != rows:
            self._reject(
                identity,
                "bad_index",
                f"{link.describe()} answered for agents outside its range or twice: "
                f"{outside[:8] or 'a repeated index'}",
            )
            return
        if isinstance(answer, Evaluation):
            self.collector.on_evaluation(identity, link, answer)
        elif self.secure is not None:
            self._reject(identity, "unexpected_type", "this run aggregates masked updates only")
        elif self.buffered:
            self.arrivals.on_update(identity, link, answer)
        else:
            self.collector.on_update(identity, link, answer)

    # -- the pool interface --------------------------------------------------------------------

    def wait_for_agents(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        peers = self.links.peers
        while len(peers) < self.num_agents:
            if time.monotonic() >= deadline:
                missing = [k for k in range(self.num_agents) if k not in peers]
                raise FederationError(
                    f"only {len(peers)} of {self.num_agents} agents registered within "
                    f"{timeout_s:g} s (server.register_timeout_s); missing: "
                    f"{index_ranges(missing)}"
                )
            self.pump(deadline - time.monotonic())

    def secure_participants(self, agents: Sequence[int]) -> list[int]:
        """The registered agents of ``agents`` with a usable channel key."""
        if self.secure is None:
            return sorted(agents)
        return self.secure.participants(self.links, agents)

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
        if private is not None:
            assert self.secure is not None
            return self.secure.round(
                self.collector,
                self.links,
                self.pump,
                round_index,
                theta,
                agents,
                private,
                budgets=budgets,
                while_training=while_training,
            )
        request = Train(round=round_index, theta=theta.detach().numpy(), agents=[])
        collection = self.collector.collect(
            request,
            "round",
            agents,
            pump=self.pump,
            budgets=budgets,
            while_waiting=while_training,
        )
        answers = self.collector.round_answers(collection)
        if answers.stragglers:
            logger.warning(
                "round %d aggregated %d of %d updates; stragglers: %s",
                round_index,
                len(answers.result),
                len(collection.expected),
                ", ".join(answers.stragglers),
            )
        return answers

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int
    ) -> dict[str, EvaluationStats]:
        request = Evaluate(
            round=round_index, theta=theta.detach().numpy(), episodes=episodes, agents=[]
        )
        collection = self.collector.collect(
            request, "evaluation of round", range(self.num_agents), pump=self.pump
        )
        self._send_trains()  # an agent that rejoined during the evaluation
        name = self.links.name
        return {
            name(k): answer
            for k, answer in sorted(collection.answers.items())
            if isinstance(answer, EvaluationStats)
        }

    # -- buffered rounds (server/buffered_zmq.py) -----------------------------------------------

    def start_trains(
        self, requests: Sequence[tuple[int, int]], version: int, theta: torch.Tensor
    ) -> None:
        """Open a request for each (agent index, its round index) from θ̃ (``version``, the
        newest) and send those whose agent is registered; the others get it on rejoining."""
        self.arrivals.start(requests, version, theta)
        self._send_trains()

    def _send_trains(self) -> None:
        if self.collector.open is None:  # an evaluation's request would be cancelled
            self.arrivals.send()

    def outstanding(self) -> int:
        """Buffered rounds: updates that may still arrive (open requests, queued arrivals)."""
        return self.arrivals.outstanding()

    def next_arrival(self) -> Arrival:
        """The next answer in arrival order (waiting for one)."""
        since = time.monotonic()
        while not self.arrivals.queue:
            self.arrivals.check_stalled(since)
            self.pump()
        return self.arrivals.queue.popleft()

    def drain(self) -> None:
        """Wait until no registered agent is training (their answers queue up as arrivals):
        evaluation pauses dispatch rather than cancel work in flight."""
        since = time.monotonic()
        while self.arrivals.training():
            self.arrivals.check_stalled(since)
            self.pump()

    # -- the end -------------------------------------------------------------------------------

    def counters(self) -> dict[str, int]:
        """What went wrong so far, for summary.json (kept across resumes by the checkpoints)."""
        return {
            "rejected_messages": self.outbox.rejected,
            "late_answers": self.collector.late_answers + self.arrivals.late_answers,
            "agent_deaths": self.links.deaths,
            "agent_rejoins": self.links.rejoins,
            "dropped_flood_messages": self.dropped,
        }

    def restore_counters(self, counters: dict[str, int]) -> None:
        self.outbox.rejected = counters.get("rejected_messages", 0)
        self.collector.late_answers = counters.get("late_answers", 0)
        self.links.deaths = counters.get("agent_deaths", 0)
        self.links.rejoins = counters.get("agent_rejoins", 0)
        self.dropped = counters.get("dropped_flood_messages", 0)

    def shutdown(self, reason: str, *, complete: bool = True) -> None:
        """Tell every agent the run is over (``complete``) or was aborted."""
        message = Shutdown(reason=reason[:1000], complete=complete)
        for link in self.links.by_identity.values():
            self.outbox.send(link.identity, message)
