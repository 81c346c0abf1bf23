"""The wire protocol in one place: message types and their typed payloads.

Every message is one frozen dataclass below. :mod:`fedhpg.common.wire.codec` turns any of them into
ZeroMQ frames (a msgpack header, then one raw frame per array field) and back; nothing here
knows about bytes. Fields typed ``np.ndarray`` travel as raw frames, every other field in the
header as plain msgpack values (None, bool, int, float, str, list, dict) or, for the typed
results of :mod:`fedhpg.common.records.types`, as maps of exactly their fields.

One family of messages serves every placement: a connection registers a range of logical
agents (``Hello.first``, ``Hello.count``), and a lone agent is a range of one. Requests name
the agents they ask (θ̃ sent once for all of them) and answers carry a row per agent, so one
agent and an agent host of thousands speak the same protocol and are checked by the same code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated, Any

import numpy as np

from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.records.limits import (
    MAX_BATCH_ANSWERS,
    MAX_HOST_AGENTS,
    AgentIndex,
    Bound,
    Name,
    Round,
    Text,
)
from fedhpg.common.records.types import EvaluationStats, RoundResult, UpdateColumns

PROTOCOL_VERSION = 10
"""Bumped whenever a message changes; a peer of another version is refused with a reason."""

KIB = 1024
BATCH_THETA_BYTES = 16 << 20
"""θ bytes one ``Update`` may carry beyond a single θ (the server's message cap grows by at
most this much, so a batch of small policies still goes in one message)."""

AgentList = Annotated[list[AgentIndex], Bound(max_len=MAX_HOST_AGENTS)]
MAX_ROUND_AGENTS = 1 << 20
"""Most agents one securely aggregated round may name."""
AnswerList = Annotated[list[AgentIndex], Bound(max_len=MAX_BATCH_ANSWERS)]
AgentCount = Annotated[int, Bound(low=1, high=MAX_HOST_AGENTS)]
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
    MASK_KEYS = "mask_keys"
    SHARE_REQUEST = "share_request"
    KEY_SHARES = "key_shares"
    MASK_REQUEST = "mask_request"
    MASKED_UPDATE = "masked_update"
    UNMASK_REQUEST = "unmask_request"
    UNMASKING = "unmasking"
    EVALUATE = "evaluate"
    EVALUATION = "evaluation"
    HEARTBEAT = "heartbeat"
    SHUTDOWN = "shutdown"
    ERROR = "error"


@dataclass(frozen=True, kw_only=True)
class Hello:
    """Agent → server: registration of the logical agents ``first`` .. ``first + count - 1``
    over this connection (a lone agent is a range of one). The environment spaces are the
    run's, computed once; ``variant_digest`` is
    :func:`fedhpg.common.heterogeneity.variants.range_digest` of the agents' variant digests
    (family, parameters, γ_k, horizon), which the server recomputes for the range, so no agent
    trains on another MDP."""

    id: Name
    """The connection's id: a lone agent's own (``agent-<k>`` by default), an agent host's
    (``host-<first>-<last>``), whose logical agents are ``agent-<k>``."""
    first: AgentIndex
    count: AgentCount
    names_agent: bool = False
    """Whether ``id`` is also the name of the range's one agent (a lone agent,
    ``agent.index=k``, perhaps ``agent.id=alice``); otherwise the agents are ``agent-<k>``."""
    env_signature: Annotated[dict[str, Text], Bound(max_len=8, key_len=64)]
    """The observation and action spaces: every agent's must be the run's."""
    variant_digest: Name
    profile: Annotated[dict[str, Any], Bound(max_len=16, key_len=64)] = field(default_factory=dict)
    """What the agent says of its compute (logged at registration)."""
    channel_keys: np.ndarray = field(default_factory=lambda: no_keys())
    """Secure aggregation: each agent's channel public key (X25519), a [count, 32] uint8 row
    per agent of the range; [0, 32] where the program cannot aggregate securely."""


KEY_BYTES = 32


def no_keys(rows: int = 0) -> np.ndarray:
    """An empty (or all-zero) [rows, 32] uint8 array of public keys."""
    return np.zeros((rows, KEY_BYTES), dtype=np.uint8)


@dataclass(frozen=True, kw_only=True)
class Welcome:
    """Server → agent: every agent of the range is registered; ``run`` holds the settings the
    server dictates (``fedhpg.common.configuration.run_roles.GROUPS``)."""

    run_id: Name
    first: AgentIndex
    count: AgentCount
    run: dict[str, Any]


@dataclass(frozen=True, kw_only=True, eq=False)
class Train:
    """Server → agent: one round's local update from ``theta`` (sent once) for each of
    ``agents`` (the connection's selected agents, ascending)."""

    round: Round
    theta: np.ndarray
    agents: AgentList
    budgets: Annotated[list[BudgetOverride], Bound(max_len=MAX_HOST_AGENTS)] = field(
        default_factory=list
    )
    """Empty (every agent its own budget) or the server's plan for each entry of ``agents``
    (``agents.plan``)."""
    private: RoundPrivacy | None = None
    """Secure aggregation: how each agent contributes (clip, its share of the noise, the
    fixed-point range); the agents answer with :class:`MaskKeys`, not an :class:`Update`."""
    participants: Annotated[list[AgentIndex], Bound(max_len=MAX_ROUND_AGENTS)] = field(
        default_factory=list
    )
    """Secure aggregation: every agent of the round (all connections'), ascending."""
    channel_keys: np.ndarray = field(default_factory=lambda: no_keys())
    """Secure aggregation: the participants' channel public keys, [len(participants), 32]."""

    def __post_init__(self) -> None:
        if self.budgets and len(self.budgets) != len(self.agents):
            raise ValueError(
                f"budgets has {len(self.budgets)} entries for {len(self.agents)} agents"
            )


Update = RoundResult
"""Agent → server: the results of ``agents`` for ``round``, the engine's
:class:`~fedhpg.common.records.types.RoundResult` itself (at most ``MAX_BATCH_ANSWERS`` rows)."""


# --- secure aggregation: the exchanges of a private round (common/privacy/secagg.py) ---------


@dataclass(frozen=True, kw_only=True, eq=False)
class MaskKeys:
    """Agent → server, after training a private round: row i is agent ``agents[i]``'s fresh
    round mask public key, its commitment to its self-mask seed, and its signature of (round,
    agent, mask key, channel key, commitment) under its roster key (all zeros where the agent
    has no roster: unsigned)."""

    round: Round
    agents: AnswerList
    mask_keys: np.ndarray
    """[A, 32] uint8."""
    seed_commitments: np.ndarray
    """[A, 32] uint8."""
    signatures: np.ndarray
    """[A, 64] uint8."""


@dataclass(frozen=True, kw_only=True, eq=False)
class ShareRequest:
    """Server → agent: every mask key advertised for the round (by ``participants``, in
    increasing order) with its seed commitment and signature; the round's graph is drawn from
    them, and each of ``agents`` answers with its shares sealed for its neighbours
    (:class:`KeyShares`)."""

    round: Round
    agents: AgentList
    participants: Annotated[list[AgentIndex], Bound(max_len=MAX_ROUND_AGENTS)]
    mask_keys: np.ndarray
    """[len(participants), 32] uint8."""
    seed_commitments: np.ndarray
    """[len(participants), 32] uint8."""
    signatures: np.ndarray
    """[len(participants), 64] uint8."""


@dataclass(frozen=True, kw_only=True, eq=False)
class KeyShares:
    """Agent → server, answering a :class:`ShareRequest`: row i is agent ``agents[i]``'s round
    mask public key (as advertised), and its secret shares sealed for each neighbour
    ``recipients[i, j]`` (−1: an unused slot)."""

    round: Round
    agents: AnswerList
    mask_keys: np.ndarray
    """[A, 32] uint8."""
    recipients: np.ndarray
    """[A, k] int64."""
    sealed: np.ndarray
    """[A, k, SEALED_BYTES] uint8."""


@dataclass(frozen=True, kw_only=True, eq=False)
class MaskRequest:
    """Server → agent: for each of ``agents`` (row i), its neighbours ``senders[i, j]`` that
    shared keys (−1: none), their mask public keys and the shares they sealed for it."""

    round: Round
    agents: AgentList
    senders: np.ndarray
    """[A, k] int64."""
    mask_keys: np.ndarray
    """[A, k, 32] uint8."""
    sealed: np.ndarray
    """[A, k, SEALED_BYTES] uint8."""


@dataclass(frozen=True, kw_only=True, eq=False)
class MaskedUpdate:
    """Agent → server: row i of ``masked`` is agent ``agents[i]``'s contribution, fixed point
    and masked ([A, d + 2] uint64 words, carried as int64), ``stats[i]`` what it cost."""

    round: Round
    agents: AnswerList
    masked: np.ndarray
    stats: UpdateColumns


@dataclass(frozen=True, kw_only=True)
class UnmaskRequest:
    """Server → agent: who shared keys but sent no input (``dropped``) and whose inputs are in
    the sum (``included``): each of ``agents`` reveals its shares accordingly."""

    round: Round
    agents: AgentList
    dropped: Annotated[list[AgentIndex], Bound(max_len=MAX_ROUND_AGENTS)]
    included: Annotated[list[AgentIndex], Bound(max_len=MAX_ROUND_AGENTS)]


@dataclass(frozen=True, kw_only=True, eq=False)
class Unmasking:
    """Agent → server: row i holds agent ``agents[i]``'s revealed shares: of agent
    ``owners[i, j]``'s secret of kind ``kinds[i, j]`` (1: mask key, 2: self-mask seed; 3: not
    a share but the pair's mask key, for a neighbour whose sealed shares did not open; owner
    −1: an unused slot). Each owner once per row."""

    round: Round
    agents: AnswerList
    owners: np.ndarray
    """[A, k] int64."""
    kinds: np.ndarray
    """[A, k] uint8."""
    shares: np.ndarray
    """[A, k, SHARE_BYTES] uint8."""


@dataclass(frozen=True, kw_only=True, eq=False)
class Evaluate:
    """Server → agent: evaluate the unified policy ``theta`` in the environment of each of
    ``agents``."""

    round: Round
    theta: np.ndarray
    episodes: Annotated[int, Bound(low=1, high=2**20)]
    agents: AgentList


@dataclass(frozen=True, kw_only=True)
class Evaluation:
    """Agent → server: ``stats[i]`` is agent ``agents[i]``'s evaluation of ``round``."""

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
    | MaskKeys
    | ShareRequest
    | KeyShares
    | MaskRequest
    | MaskedUpdate
    | UnmaskRequest
    | Unmasking
    | Evaluate
    | Evaluation
    | Heartbeat
    | Shutdown
    | Error
)
Request = Train | ShareRequest | MaskRequest | UnmaskRequest | Evaluate
"""What the server asks of an agent; a newer request supersedes the one in flight."""
SecureAnswer = MaskKeys | KeyShares | MaskedUpdate | Unmasking
"""An agent's answers in a securely aggregated round."""

PAYLOAD_TYPES: dict[str, type] = {  # keyed by MsgType, a str: decode looks up plain str
    MsgType.HELLO: Hello,
    MsgType.WELCOME: Welcome,
    MsgType.TRAIN: Train,
    MsgType.UPDATE: Update,
    MsgType.MASK_KEYS: MaskKeys,
    MsgType.SHARE_REQUEST: ShareRequest,
    MsgType.KEY_SHARES: KeyShares,
    MsgType.MASK_REQUEST: MaskRequest,
    MsgType.MASKED_UPDATE: MaskedUpdate,
    MsgType.UNMASK_REQUEST: UnmaskRequest,
    MsgType.UNMASKING: Unmasking,
    MsgType.EVALUATE: Evaluate,
    MsgType.EVALUATION: Evaluation,
    MsgType.HEARTBEAT: Heartbeat,
    MsgType.SHUTDOWN: Shutdown,
    MsgType.ERROR: Error,
}
HEADER_LIMITS: dict[type, int] = {
    Hello: 64 * KIB,
    Update: 4 * KIB + MAX_BATCH_ANSWERS * 3 * KIB,
    MaskedUpdate: 4 * KIB + MAX_BATCH_ANSWERS * 3 * KIB,
    MaskKeys: 4 * KIB + MAX_BATCH_ANSWERS * 16,
    KeyShares: 4 * KIB + MAX_BATCH_ANSWERS * 16,
    Unmasking: 4 * KIB + MAX_BATCH_ANSWERS * 16,
    Evaluation: 1 * KIB + MAX_BATCH_ANSWERS * 1 * KIB,
    Heartbeat: 1 * KIB,
    Shutdown: 16 * KIB,
    Error: 16 * KIB,
}
"""Largest header of a message type (the codec's MAX_HEADER_BYTES for the rest, which only the
server sends): a peer cannot make a small message big."""
HEADER_PER_AGENT: dict[type, tuple[str, int, int]] = {
    Update: ("agents", 4 * KIB, 3 * KIB),
    MaskedUpdate: ("agents", 4 * KIB, 3 * KIB),
    Evaluation: ("agents", 1 * KIB, 1 * KIB),
}
"""Answers: (list field, base, bytes per agent). After decoding, a header may be at most
base + per agent × the agents it lists, as if each agent had sent its own message (an
``UpdateStats`` with all 32 algorithm statistics takes ~2.6 KiB)."""
MSG_TYPE_OF: dict[type, str] = {cls: kind for kind, cls in PAYLOAD_TYPES.items()}
