"""The wire protocol in one place: message types and their typed payloads.

Every message is one frozen dataclass below. :mod:`fedhpg.common.wire.codec` turns any of them into
ZeroMQ frames (a msgpack header, then one raw frame per array field) and back; nothing here
knows about bytes. Fields typed ``np.ndarray`` travel as raw frames, every other field in the
header as plain msgpack values (None, bool, int, float, str, list, dict) or, for the typed
results of :mod:`fedhpg.common.types`, as maps of exactly their fields.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Annotated, Any, overload

import numpy as np

from fedhpg.common.limits import (
    MAX_HOST_AGENTS,
    AgentIndex,
    Bound,
    Count,
    Finite,
    Name,
    Round,
    Seconds,
    Speed,
    Text,
)
from fedhpg.common.types import ALGORITHM_STATS, EvaluationStats, UpdateStats

PROTOCOL_VERSION = 6
"""2: typed ``Update.stats`` / ``Evaluation.stats``; ``Hello.variant_digest``.
3: every field bounded (:mod:`fedhpg.common.limits`); ``Shutdown.complete``.
4: agent hosts (``HostHello`` .. ``EvaluationBatch``): many logical agents, one connection.
5: ``Train.budget`` / ``TrainBatch.budgets``: the round's budget (``agents.plan``).
6: ``UpdateBatch.stats`` as columns (:class:`UpdateColumns`), not one map per agent."""

KIB = 1024
MAX_BATCH_ANSWERS = 256
"""Most agents' answers in one ``UpdateBatch`` / ``EvaluationBatch``: a host sends a round's
answers in ceil(A / this) messages (fewer agents per message where θ is large)."""
BATCH_THETA_BYTES = 16 << 20
"""θ bytes one ``UpdateBatch`` may carry beyond a single θ (the server's message cap grows by
at most this much, so a batch of small policies still goes in one message)."""

AgentList = Annotated[list[AgentIndex], Bound(max_len=MAX_HOST_AGENTS)]
AnswerList = Annotated[list[AgentIndex], Bound(max_len=MAX_BATCH_ANSWERS)]
MAX_BUDGET = 1 << 20
"""Largest budget count (trajectories per batch, local iterations) a request may set."""
BudgetCount = Annotated[int, Bound(low=1, high=MAX_BUDGET)]
BudgetOverride = Annotated[dict[str, BudgetCount], Bound(max_len=8, key_len=64)]
"""Fields of the algorithm's ``Budget`` to use this round instead of the agent's configured
ones (``{"batch_size": 12, "local_iters": 2}``); empty: the configured budget."""


class MsgType(StrEnum):
    HELLO = "hello"
    WELCOME = "welcome"
    TRAIN = "train"
    UPDATE = "update"
    EVALUATE = "evaluate"
    EVALUATION = "evaluation"
    HOST_HELLO = "host_hello"
    HOST_WELCOME = "host_welcome"
    TRAIN_BATCH = "train_batch"
    UPDATE_BATCH = "update_batch"
    EVALUATE_BATCH = "evaluate_batch"
    EVALUATION_BATCH = "evaluation_batch"
    HEARTBEAT = "heartbeat"
    SHUTDOWN = "shutdown"
    ERROR = "error"


@dataclass(frozen=True, kw_only=True)
class Hello:
    """Agent → server: registration with the agent's environment signature and variant."""

    agent_id: Name
    agent_index: AgentIndex
    env_signature: Annotated[dict[str, Text], Bound(max_len=8, key_len=64)]
    """The observation and action spaces: every agent's must be the run's."""
    variant_digest: Name = ""
    """Digest of the agent's environment variant (family, parameters, γ_k, horizon): must be
    the one the server expects for ``agent_index``, so no host trains on another MDP."""
    profile: Annotated[dict[str, Any], Bound(max_len=16, key_len=64)] = field(default_factory=dict)
    """What the agent says of its compute (logged at registration)."""


@dataclass(frozen=True, kw_only=True)
class Welcome:
    """Server → agent: registration accepted; ``run`` holds the settings the server dictates
    (``fedhpg.common.config.GROUPS``)."""

    run_id: Name
    agent_index: AgentIndex
    run: dict[str, Any]


@dataclass(frozen=True, kw_only=True, eq=False)
class Train:
    """Server → agent: run one round's local update from ``theta``."""

    round: Round
    theta: np.ndarray
    budget: BudgetOverride = field(default_factory=dict)
    """The server's plan for this agent's round (``agents.plan``); empty: its own budget."""


@dataclass(frozen=True, kw_only=True, eq=False)
class Update:
    """Agent → server: the local result θ_k of ``round`` and what it cost."""

    round: Round
    theta: np.ndarray
    stats: UpdateStats


@dataclass(frozen=True, kw_only=True, eq=False)
class Evaluate:
    """Server → agent: evaluate the unified policy ``theta`` in the agent's environment."""

    round: Round
    theta: np.ndarray
    episodes: Annotated[int, Bound(low=1, high=2**20)]


@dataclass(frozen=True, kw_only=True)
class Evaluation:
    """Agent → server: evaluation results for ``round``."""

    round: Round
    stats: EvaluationStats


@dataclass(frozen=True, kw_only=True)
class HostHello:
    """Host → server: registration of the logical agents ``first`` .. ``first + count - 1``
    (ids ``agent-<k>``) in one message. The environment spaces are the run's, computed once;
    ``variant_digest`` is :func:`fedhpg.common.variants.range_digest` of the agents' digests,
    which the server recomputes for the range."""

    host_id: Name
    first: AgentIndex
    count: Annotated[int, Bound(low=1, high=MAX_HOST_AGENTS)]
    env_signature: Annotated[dict[str, Text], Bound(max_len=8, key_len=64)]
    variant_digest: Name
    profile: Annotated[dict[str, Any], Bound(max_len=16, key_len=64)] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class HostWelcome:
    """Server → host: every agent of the range is registered; ``run`` as in ``Welcome``."""

    run_id: Name
    first: AgentIndex
    count: Annotated[int, Bound(low=1, high=MAX_HOST_AGENTS)]
    run: dict[str, Any]


@dataclass(frozen=True, kw_only=True, eq=False)
class TrainBatch:
    """Server → host: one round's local update from ``theta`` (sent once) for each of
    ``agents`` (the host's selected agents, ascending)."""

    round: Round
    theta: np.ndarray
    agents: AgentList
    budgets: Annotated[list[BudgetOverride], Bound(max_len=MAX_HOST_AGENTS)] = field(
        default_factory=list
    )
    """Empty (every agent its own budget) or one override per entry of ``agents``."""

    def __post_init__(self) -> None:
        if self.budgets and len(self.budgets) != len(self.agents):
            raise ValueError(
                f"budgets has {len(self.budgets)} entries for {len(self.agents)} agents"
            )


CountColumn = Annotated[list[Count], Bound(max_len=MAX_BATCH_ANSWERS)]
SecondsColumn = Annotated[list[Seconds], Bound(max_len=MAX_BATCH_ANSWERS)]
FiniteColumn = Annotated[list[Finite], Bound(max_len=MAX_BATCH_ANSWERS)]
SpeedColumn = Annotated[list[Speed], Bound(max_len=MAX_BATCH_ANSWERS)]
MaybeSecondsColumn = Annotated[list[Seconds | None], Bound(max_len=MAX_BATCH_ANSWERS)]
MaybeFiniteColumn = Annotated[list[Finite | None], Bound(max_len=MAX_BATCH_ANSWERS)]
AlgorithmColumns = Annotated[
    dict[str, MaybeFiniteColumn], Bound(max_len=ALGORITHM_STATS, key_len=64)
]


@dataclass(frozen=True, kw_only=True)
class UpdateColumns(Sequence[UpdateStats]):
    """The :class:`~fedhpg.common.types.UpdateStats` of a batch's agents, one list per field
    (item i is the batch's agent i's), read as a sequence of records.

    A host's batch carries hundreds of records; as one map each, encoding and checking them
    cost ~12 µs per agent on each side, and the server pays that for every agent every
    round. As columns the codec checks a whole column in a few C-level passes
    (:func:`fedhpg.common.wire.codec._all_fit`) and the bounds are the records' own. The
    fields mirror ``UpdateStats`` one for one (tested)."""

    trajectories: CountColumn
    env_steps: CountColumn
    compute_s: SecondsColumn
    train_return: FiniteColumn
    grad_clipped: CountColumn
    emulated_s: SecondsColumn
    speed: SpeedColumn
    local_wall_s: MaybeSecondsColumn
    algorithm: AlgorithmColumns
    """Each algorithm statistic's column; None where an agent did not report it."""

    def __post_init__(self) -> None:
        lengths = {name: len(getattr(self, name)) for name in _SCALAR_COLUMNS}
        lengths |= {f"algorithm[{key!r}]": len(column) for key, column in self.algorithm.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"columns of different lengths: {lengths}")

    @classmethod
    def of(cls, records: Sequence[UpdateStats]) -> UpdateColumns:
        names = dict.fromkeys(key for record in records for key in record.algorithm)
        return cls(
            **{name: [getattr(r, name) for r in records] for name in _SCALAR_COLUMNS},
            algorithm={key: [r.algorithm.get(key) for r in records] for key in names},
        )

    def take(self, rows: Sequence[int]) -> UpdateColumns:
        """The columns of ``rows`` only, in that order."""
        return UpdateColumns(
            **{name: [getattr(self, name)[i] for i in rows] for name in _SCALAR_COLUMNS},
            algorithm={key: [column[i] for i in rows] for key, column in self.algorithm.items()},
        )

    def __len__(self) -> int:
        return len(self.trajectories)

    @overload
    def __getitem__(self, index: int) -> UpdateStats: ...

    @overload
    def __getitem__(self, index: slice) -> UpdateColumns: ...

    def __getitem__(self, index: int | slice) -> UpdateStats | UpdateColumns:
        if isinstance(index, slice):  # the columns' own slices: a host cuts its batch so
            return UpdateColumns(
                **{name: getattr(self, name)[index] for name in _SCALAR_COLUMNS},
                algorithm={key: column[index] for key, column in self.algorithm.items()},
            )
        return UpdateStats(
            trajectories=self.trajectories[index],
            env_steps=self.env_steps[index],
            compute_s=self.compute_s[index],
            train_return=self.train_return[index],
            grad_clipped=self.grad_clipped[index],
            emulated_s=self.emulated_s[index],
            speed=self.speed[index],
            local_wall_s=self.local_wall_s[index],
            algorithm={
                key: value
                for key, column in self.algorithm.items()
                if (value := column[index]) is not None
            },
        )

    def __iter__(self) -> Iterator[UpdateStats]:
        return iter(self.records())

    def records(self) -> list[UpdateStats]:
        """Every row's record (what ``self[i]`` gives for each i), built in one pass over the
        columns: a server reads a host's 500 records so each round."""
        algorithm = (
            [
                {
                    key: value
                    for key, value in zip(self.algorithm, values, strict=True)
                    if value is not None
                }
                for values in zip(*self.algorithm.values(), strict=True)
            ]
            if self.algorithm
            else [{} for _ in range(len(self))]
        )
        return [
            UpdateStats(
                trajectories=trajectories,
                env_steps=env_steps,
                compute_s=compute_s,
                train_return=train_return,
                grad_clipped=grad_clipped,
                emulated_s=emulated_s,
                speed=speed,
                local_wall_s=local_wall_s,
                algorithm=own,
            )
            for (
                trajectories, env_steps, compute_s, train_return, grad_clipped, emulated_s, speed,
                local_wall_s, own,
            ) in zip(
                self.trajectories, self.env_steps, self.compute_s, self.train_return,
                self.grad_clipped, self.emulated_s, self.speed, self.local_wall_s, algorithm,
                strict=True,
            )
        ]  # fmt: skip


_SCALAR_COLUMNS = tuple(f.name for f in fields(UpdateStats) if f.name != "algorithm")


@dataclass(frozen=True, kw_only=True, eq=False)
class UpdateBatch:
    """Host → server: the results of ``agents`` for ``round``: row i of ``thetas`` (an
    [A, d] float32 array) and ``stats[i]`` are agent ``agents[i]``'s."""

    round: Round
    agents: AnswerList
    thetas: np.ndarray
    stats: UpdateColumns


@dataclass(frozen=True, kw_only=True, eq=False)
class EvaluateBatch:
    """Server → host: evaluate ``theta`` in the environment of each of ``agents``."""

    round: Round
    theta: np.ndarray
    episodes: Annotated[int, Bound(low=1, high=2**20)]
    agents: AgentList


@dataclass(frozen=True, kw_only=True)
class EvaluationBatch:
    """Host → server: ``stats[i]`` is agent ``agents[i]``'s evaluation of ``round``."""

    round: Round
    agents: AnswerList
    stats: Annotated[list[EvaluationStats], Bound(max_len=MAX_BATCH_ANSWERS)]


@dataclass(frozen=True, kw_only=True)
class Heartbeat:
    """Either direction: I am alive."""


@dataclass(frozen=True, kw_only=True)
class Shutdown:
    """Server → agent: the run is over; ``complete`` says whether it finished or was aborted
    (the agent exits 0 or 1 accordingly)."""

    reason: Text
    complete: bool = True


@dataclass(frozen=True, kw_only=True)
class Error:
    """Either direction: the last message was rejected, and why."""

    code: Name
    reason: Text


Message = (
    Hello
    | Welcome
    | Train
    | Update
    | Evaluate
    | Evaluation
    | HostHello
    | HostWelcome
    | TrainBatch
    | UpdateBatch
    | EvaluateBatch
    | EvaluationBatch
    | Heartbeat
    | Shutdown
    | Error
)

PAYLOAD_TYPES: dict[str, type] = {  # keyed by MsgType, a str: decode looks up plain str
    MsgType.HELLO: Hello,
    MsgType.WELCOME: Welcome,
    MsgType.TRAIN: Train,
    MsgType.UPDATE: Update,
    MsgType.EVALUATE: Evaluate,
    MsgType.EVALUATION: Evaluation,
    MsgType.HOST_HELLO: HostHello,
    MsgType.HOST_WELCOME: HostWelcome,
    MsgType.TRAIN_BATCH: TrainBatch,
    MsgType.UPDATE_BATCH: UpdateBatch,
    MsgType.EVALUATE_BATCH: EvaluateBatch,
    MsgType.EVALUATION_BATCH: EvaluationBatch,
    MsgType.HEARTBEAT: Heartbeat,
    MsgType.SHUTDOWN: Shutdown,
    MsgType.ERROR: Error,
}
HEADER_LIMITS: dict[type, int] = {
    Hello: 64 * KIB,
    Update: 64 * KIB,
    Evaluation: 16 * KIB,
    HostHello: 64 * KIB,
    UpdateBatch: 4 * KIB + MAX_BATCH_ANSWERS * 3 * KIB,
    EvaluationBatch: 1 * KIB + MAX_BATCH_ANSWERS * 1 * KIB,
    Heartbeat: 1 * KIB,
    Shutdown: 16 * KIB,
    Error: 16 * KIB,
}
"""Largest header of a message type (the codec's MAX_HEADER_BYTES for the rest, which only the
server sends): a peer cannot make a small message big."""
HEADER_PER_AGENT: dict[type, tuple[str, int, int]] = {
    UpdateBatch: ("agents", 4 * KIB, 3 * KIB),
    EvaluationBatch: ("agents", 1 * KIB, 1 * KIB),
}
"""Batched answers: (list field, base, bytes per agent). After decoding, a header may be at
most base + per agent × the agents it lists, as if each agent had sent its own message (an
``UpdateStats`` with all 32 algorithm statistics takes ~2.6 KiB)."""
MSG_TYPE_OF: dict[type, str] = {cls: kind for kind, cls in PAYLOAD_TYPES.items()}
