"""The wire protocol in one place: message types and their typed payloads.

Every message is one frozen dataclass below. :mod:`fedhpg.common.wire.codec` turns any of them into
ZeroMQ frames (a msgpack header, then one raw frame per array field) and back; nothing here
knows about bytes. Fields typed ``np.ndarray`` travel as raw frames, every other field in the
header as plain msgpack values (None, bool, int, float, str, list, dict) or, for the typed
results of :mod:`fedhpg.common.types`, as maps of exactly their fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated, Any

import numpy as np

from fedhpg.common.limits import AgentIndex, Bound, Name, Round, Text
from fedhpg.common.types import EvaluationStats, UpdateStats

PROTOCOL_VERSION = 3
"""2: typed ``Update.stats`` / ``Evaluation.stats``; ``Hello.variant_digest``.
3: every field bounded (:mod:`fedhpg.common.limits`); ``Shutdown.complete``."""

KIB = 1024


class MsgType(StrEnum):
    HELLO = "hello"
    WELCOME = "welcome"
    TRAIN = "train"
    UPDATE = "update"
    EVALUATE = "evaluate"
    EVALUATION = "evaluation"
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


Message = Hello | Welcome | Train | Update | Evaluate | Evaluation | Heartbeat | Shutdown | Error

PAYLOAD_TYPES: dict[str, type] = {  # keyed by MsgType, a str: decode looks up plain str
    MsgType.HELLO: Hello,
    MsgType.WELCOME: Welcome,
    MsgType.TRAIN: Train,
    MsgType.UPDATE: Update,
    MsgType.EVALUATE: Evaluate,
    MsgType.EVALUATION: Evaluation,
    MsgType.HEARTBEAT: Heartbeat,
    MsgType.SHUTDOWN: Shutdown,
    MsgType.ERROR: Error,
}
HEADER_LIMITS: dict[type, int] = {
    Hello: 64 * KIB,
    Update: 64 * KIB,
    Evaluation: 16 * KIB,
    Heartbeat: 1 * KIB,
    Shutdown: 16 * KIB,
    Error: 16 * KIB,
}
"""Largest header of a message type (the codec's MAX_HEADER_BYTES for the rest, which only the
server sends): a peer cannot make a small message big."""
MSG_TYPE_OF: dict[type, str] = {cls: kind for kind, cls in PAYLOAD_TYPES.items()}
