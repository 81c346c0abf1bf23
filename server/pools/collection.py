"""A request and its answers: one synchronous round's ``Train``, or an ``Evaluate``.

:class:`Collector` holds the one request open at a time (a :class:`Collection`): which agents
were asked, which answered (accepted, or rejected: a rejection counts as the agent's answer, it
is not waited for), and, for a round, the accepted θ_k. It says what a link is still owed
(:meth:`Collector.request_for`: the request names the link's selected agents that have not
answered, so a link that rejoins is asked again for exactly those), files each answer's rows
for their own agents as if each had come alone, and discards answers for a request no longer
open with a log line. The round policy (:mod:`fedhpg.server.pools.rounds`) decides when a
collection is complete.

Every row of an ``Update`` passes the same :class:`~fedhpg.server.validation.UpdateCheck` as
in the in-process pool, each pass over the [A, d] matrix made once for all its rows; a bad row
rejects that agent only. Accepted θ_k are copied once, on arrival, into the round's
:class:`~fedhpg.server.round_rows.RoundRows` (the frames are then let go); the round's
:class:`~fedhpg.common.records.types.RoundResult` holds that matrix (or a compact copy of its
accepted rows) and the statistics of its rows, gathered from each message's columns.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.records.types import RoundResult, UpdateColumns
from fedhpg.common.runtime import timeline
from fedhpg.common.wire.protocol import (
    Evaluation,
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    Request,
    SecureAnswer,
    ShareRequest,
    Train,
    Unmasking,
    UnmaskRequest,
    Update,
)
from fedhpg.server.pools import RoundAnswers
from fedhpg.server.pools.links import Link, Links, Outbox
from fedhpg.server.pools.rounds import request_complete
from fedhpg.server.round_rows import RoundRows
from fedhpg.server.validation import Reject, Rejection, UpdateCheck


@dataclass
class Collection:
    """One request sent to the selected agents and its answers."""

    request: Request
    """The request, naming no agents (each link is sent it for its own)."""
    expected: frozenset[int]
    """The agents asked (the strategy's selection; every agent for an evaluation)."""
    started: float = field(default_factory=time.monotonic)
    answers: dict[int, Any] = field(default_factory=dict)
    """Agent index → its answer: (an ``Update``'s stats, its row) for a round,
    ``EvaluationStats``, or one row of a secure aggregation's answer (:data:`SECURE_ANSWER`)."""
    failures: dict[int, Rejection] = field(default_factory=dict)
    """Agents whose answer was rejected (it counts as their answer: they are not waited for)."""
    rows: RoundRows | None = None
    """A round's accepted θ_k (None for an evaluation), copied in as they arrive."""
    budgets: Mapping[int, Mapping[str, int]] = field(default_factory=dict)
    """A round's planned budgets (``agents.plan``), by agent index; empty: their own."""
    rows_for: Callable[[list[int]], Request] | None = None
    """A request whose content differs per agent (secure aggregation's routed shares): the
    message for the given agents; None: the request, naming them."""
    phase: bool = False
    """A secure aggregation's exchange after training: closed once every live agent asked
    answered, or after ``server.round_deadline_s`` (the others drop out of the round)."""

    @property
    def answer_type(self) -> type:
        """What answers this request."""
        request = self.request
        if isinstance(request, Train):
            return MaskKeys if request.private is not None else Update
        return SECURE_ANSWER.get(type(request), Evaluation)

    @property
    def round(self) -> int:
        return self.request.round

    @property
    def is_train(self) -> bool:
        return isinstance(self.request, Train)

    def answered(self, index: int) -> bool:
        return index in self.answers or index in self.failures

    def awaits(self, index: int) -> bool:
        """Whether agent ``index`` was asked and has not answered."""
        return index in self.expected and not self.answered(index)


SECURE_ANSWER: dict[type, type] = {
    ShareRequest: KeyShares,
    MaskRequest: MaskedUpdate,
    UnmaskRequest: Unmasking,
}
"""The answer to each request of a secure aggregation's exchanges after training."""


class Collector:
    """The open request, if any, and what arrives for it."""

    def __init__(
        self, *, links: Links, outbox: Outbox, check: UpdateCheck, settings: ServerConfig
    ) -> None:
        self.links = links
        self.outbox = outbox
        self.check = check
        self.settings = settings
        self.open: Collection | None = None
        self.late_answers = 0

    def request_for(self, link: Link, agents: Sequence[int] | None = None) -> Request | None:
        """The open request as ``link`` gets it: naming those of ``agents`` (by default the
        link's agents) still unanswered; None if it owes nothing."""
        collection = self.open
        if collection is None:
            return None
        candidates = link.indices if agents is None else agents
        owed = [k for k in candidates if collection.awaits(k)]
        if not owed:
            return None
        if collection.rows_for is not None:
            return collection.rows_for(owed)
        request = collection.request
        if isinstance(request, Train):
            planned = collection.budgets
            budgets = [dict(planned.get(k, {})) for k in owed] if planned else []
            return dataclasses.replace(request, agents=owed, budgets=budgets)
        return dataclasses.replace(request, agents=owed)

    def owed_by(self, indices: Sequence[int]) -> int:
        """How many of ``indices`` the open request still waits for."""
        collection = self.open
        return 0 if collection is None else sum(collection.awaits(k) for k in indices)

    def collect(
        self,
        request: Request,
        what: str,
        agents: Sequence[int],
        *,
        pump: Callable[[], None],
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        while_waiting: Callable[[], None] | None = None,
        rows_for: Callable[[list[int]], Request] | None = None,
        phase: bool = False,
    ) -> Collection:
        """Send ``request`` to the selected agents, one message per link naming its selected
        agents, and ``pump`` the socket until the round policy says the answers are enough;
        ``while_waiting`` is called once the requests are out, before any answer is read.
        ``rows_for`` and ``phase``: a secure aggregation's exchange (:class:`Collection`)."""
        expected = frozenset(agents)
        is_train = isinstance(request, Train)
        plain = is_train and request.private is None  # type: ignore[union-attr]
        collection = Collection(
            request=request,
            expected=expected,
            rows=RoundRows(expected, self.check.num_params) if plain else None,
            budgets=budgets or {},
            rows_for=rows_for,
            phase=phase,
        )
        self.open = collection
        by_link: dict[bytes, tuple[Link, list[int]]] = {}
        for index in sorted(expected):
            peer = self.links.peers.get(index)
            if peer is not None:
                by_link.setdefault(peer.link.identity, (peer.link, []))[1].append(index)
        for link, selected in by_link.values():
            message = self.request_for(link, selected)
            if message is not None:
                self.links.send(link, message)
        # the marks' names: nothing formatted per round
        timeline.mark("server", "train-sent" if is_train else "evaluate-sent", request.round)
        try:
            if while_waiting is not None:
                while_waiting()
            while not self._complete(collection, what):
                pump()
        finally:
            self.open = None
        timeline.mark(
            "server", "train-collected" if is_train else "evaluate-collected", request.round
        )
        return collection

    def _complete(self, collection: Collection, what: str) -> bool:
        now = time.monotonic()
        if collection.phase:
            live = self.links.peers
            waiting = [k for k in collection.expected if collection.awaits(k) and k in live]
            elapsed = now - collection.started
            return not waiting or elapsed > self.settings.round_deadline_s
        return request_complete(
            settings=self.settings,
            what=f"{what} {collection.round}",
            expected=collection.expected,
            answered=collection.answers.keys() | collection.failures.keys(),
            accepted=len(collection.answers),
            live=self.links.peers.keys(),
            absent_since=self.links.absent_since,
            elapsed_s=now - collection.started,
            now=now,
            name=self.links.name,
        )

    def round_answers(self, collection: Collection) -> RoundAnswers:
        """A collected round as the coordinator takes it (stragglers named in a log line)."""
        name = self.links.name
        stragglers = [name(k) for k in sorted(collection.expected) if not collection.answered(k)]
        accepted = sorted(collection.answers.items())
        assert collection.rows is not None
        if not accepted:
            result = RoundResult.empty(collection.round, collection.rows.matrix.shape[1])
        else:
            parts = [stats_row for _, stats_row in accepted]
            agents = [k for k, _ in accepted]
            result = RoundResult(
                round=collection.round,
                agents=agents,
                # the one [K, d] matrix the rows were copied into as they arrived
                thetas=collection.rows.block(agents),
                stats=UpdateColumns.gathered(parts),
            )
        return RoundAnswers(
            result=result,
            name=name,
            failures={name(k): r for k, r in sorted(collection.failures.items())},
            stragglers=stragglers,
        )

    # -- answers -------------------------------------------------------------------------------

    def _open_for(self, index: int, round_index: int, train: bool) -> bool:
        """Whether an answer of agent ``index`` for ``round_index`` (to a ``Train``, or an
        ``Evaluate``) belongs to the open request; logs if not."""
        collection = self.open
        if (
            collection is not None
            and collection.is_train == train
            and collection.round == round_index
            and collection.awaits(index)
        ):
            return True
        self.late_answers += 1
        self.outbox.noisy.warning(
            "discarded a late %s from %s for round %d (no longer open)",
            "update" if train else "evaluation",
            self.links.name(index),
            round_index,
        )
        return False

    def on_update(self, identity: bytes, link: Link, update: Update) -> None:
        """A link's updates, row by row as if each had come alone, but checked and copied a
        message at a time."""
        timeline.mark("server", "batch", update.round)
        collection = self.open
        open_round = (
            collection is not None and collection.is_train and collection.round == update.round
        )
        request = collection.request if open_round and collection else None
        broadcast = request.theta if isinstance(request, Train) else None
        # decoded stats are within their bounds: the codec enforced them field by field
        problems = self.check.problems(update.thetas, update.stats, broadcast, stats_bounded=True)
        indices: list[int] = []
        rows: list[int] = []
        for i, index in enumerate(update.agents):
            if not self.links.owns(link, index):
                continue  # an agent this link lost to another (it was presumed dead)
            problem = problems[i]
            if problem is not None:
                self.outbox.reject(
                    identity, "bad_update", f"{self.links.name(index)}: {problem}", registered=True
                )
                if self._open_for(index, update.round, train=True):
                    assert self.open is not None
                    self.open.failures[index] = problem
            elif (open_round and collection is not None and collection.awaits(index)) or (
                self._open_for(index, update.round, train=True)  # not awaited: logged as late
            ):
                indices.append(index)
                rows.append(i)
        if not indices:
            return
        assert self.open is not None and self.open.rows is not None
        self.open.rows.put(indices, update.thetas, rows)  # the frames can then be let go
        for index, i in zip(indices, rows, strict=True):
            self.open.answers[index] = (update.stats, i)

    def on_secure(self, link: Link, answer: SecureAnswer) -> None:
        """A secure aggregation's answer: each row filed for its own agent (the values are
        checked where they are used, by the protocol)."""
        collection = self.open
        if (
            collection is None
            or not isinstance(answer, collection.answer_type)
            or collection.round != answer.round
        ):
            self.late_answers += 1
            self.outbox.noisy.warning(
                "discarded a late %s from %s for round %d (no longer open)",
                type(answer).__name__,
                link.describe(),
                answer.round,
            )
            return
        for row, index in enumerate(answer.agents):
            if self.links.owns(link, index) and collection.awaits(index):
                collection.answers[index] = (answer, row)

    def on_evaluation(self, identity: bytes, link: Link, evaluation: Evaluation) -> None:
        """A link's evaluations, each filed for its own agent."""
        for index, stats in zip(evaluation.agents, evaluation.stats, strict=True):
            if not self.links.owns(link, index):
                continue  # an agent this link lost to another (it was presumed dead)
            problems = stats.problems()
            if problems:
                problem = "evaluation stats: " + "; ".join(problems)
                self.outbox.reject(identity, "bad_evaluation", problem, registered=True)
                if self._open_for(index, evaluation.round, train=False):
                    assert self.open is not None
                    self.open.failures[index] = Rejection(Reject.STATS, problem)
            elif self._open_for(index, evaluation.round, train=False):
                assert self.open is not None
                self.open.answers[index] = stats
