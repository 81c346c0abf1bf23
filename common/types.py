"""One agent's work in one round, typed end to end.

The algorithm returns a :class:`LocalResult` (θ_k and :class:`UpdateStats`); the agent that
emulates the device fills in the device fields; several agents' stats travel together as
:class:`UpdateColumns`, whose columns are generated from ``UpdateStats``'s fields (the codec
checks every column against these annotations); the server holds an :class:`AgentUpdate` per
agent, which strategies aggregate and ``metrics.jsonl`` records. An evaluation travels as
:class:`EvaluationStats`. torch is imported for type checking only.
"""

from __future__ import annotations

import dataclasses
import operator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any

from fedhpg.common.columns import Columns, columns_of
from fedhpg.common.limits import (
    MAX_BATCH_ANSWERS,
    MAX_COUNT,
    Bound,
    Count,
    Finite,
    Fraction,
    Seconds,
    Speed,
    record_problems,
)

if TYPE_CHECKING:
    import numpy as np
    import torch


ALGORITHM_STATS = 32
"""Most entries an algorithm may report per round (``UpdateStats.algorithm``)."""


@dataclass(frozen=True, kw_only=True)
class UpdateStats:
    """What one round's local update cost and measured (``metrics.jsonl``'s ``agents[]``).

    Every field is bounded (:mod:`fedhpg.common.limits`): the codec refuses values out of
    range, and the server's update check applies the same bounds to in-process updates.
    """

    trajectories: Count
    """Trajectories sampled this round (B_k·τ_k for FedHPG, B_k + N·b_k for FedHPGVR)."""
    env_steps: Count
    """Environment steps of those trajectories (steps after an episode's end not counted)."""
    compute_s: Seconds
    """CPU time of the local update on the agent's thread (sampling, estimation, steps)."""
    train_return: Finite
    """Mean undiscounted return of the round's training trajectories."""
    grad_clipped: Count = 0
    """Local steps whose gradient was clipped to ``algo.grad_clip``."""
    emulated_s: Seconds = 0.0
    """Emulated device time: compute_s / speed + env_steps × step_delay_s (+ latency)."""
    speed: Speed = 1.0
    """The device speed during the round (after the schedule)."""
    local_wall_s: Seconds | None = None
    """Wall time the agent process spent on the round, sleeps included (distributed only)."""
    algorithm: Annotated[dict[str, Finite], Bound(max_len=ALGORITHM_STATS, key_len=64)] = field(
        default_factory=dict
    )
    """The algorithm's own per-round statistics (FedHPGVR: ``iw_mean``, ``iw_max``, ...)."""

    def problems(self) -> list[str]:
        """The bounds these stats break (none when they came through the codec)."""
        return record_problems(self)

    def to_json(self) -> dict[str, Any]:
        """The flat ``agents[]`` entry of metrics.jsonl (schema 1): algorithm stats inline,
        ``local_wall_s`` only where it was measured."""
        # the field names once per class, not dataclasses.fields() per call: metrics.jsonl
        # takes this for every agent of every round (1,000 rows a round at K = 1,000), while
        # the next round's agents train on the same cores
        values = dict(zip(ALWAYS_FIELDS, _always_values(self), strict=True))
        if self.local_wall_s is not None:
            values["local_wall_s"] = self.local_wall_s
        for name, value in self.algorithm.items():
            values[name] = float(value)
        return values


@columns_of(UpdateStats, rows=MAX_BATCH_ANSWERS)
class UpdateColumns(Columns[UpdateStats]):
    """The :class:`UpdateStats` of several agents, one list per field (item i is row i's),
    read as a sequence of records; its fields are generated from ``UpdateStats``'s
    (:func:`~fedhpg.common.columns.columns_of`), each column bounded as the field is.

    The one shape of a round's statistics from the agent's device pricing to the server:
    ``Update.stats`` on the wire, where the codec checks a whole column in a few C-level
    passes instead of one record at a time."""


_STATS_FIELDS = tuple(f.name for f in dataclasses.fields(UpdateStats))
_OPTIONAL_FIELDS = ("local_wall_s", "algorithm")
"""Written only where measured, and the algorithm's own, inline: the fields after the others."""
assert _STATS_FIELDS[-len(_OPTIONAL_FIELDS) :] == _OPTIONAL_FIELDS, "to_json's key order"
ALWAYS_FIELDS = _STATS_FIELDS[: -len(_OPTIONAL_FIELDS)]
"""The numbers every ``agents[]`` row of metrics.jsonl holds (schema 1)."""
_always_values = operator.attrgetter(*ALWAYS_FIELDS)


@dataclass(frozen=True, kw_only=True)
class EvaluationStats:
    """The unified policy's performance over ``episodes`` episodes in one agent's environment."""

    return_mean: Finite
    return_std: Finite
    discounted_return_mean: Finite
    """Mean return discounted with that agent's γ_k."""
    success_rate: Fraction
    """Fraction of episodes that reached the goal (0 where the env has no goal)."""
    length_mean: Annotated[float, Bound(low=0.0, high=MAX_COUNT, finite=True)]
    episodes: Annotated[int, Bound(low=1, high=MAX_COUNT)]

    def problems(self) -> list[str]:
        return record_problems(self)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, kw_only=True)
class LocalResult:
    """What an algorithm's local update returns: θ_k (a flat float32 tensor) and its stats."""

    theta: torch.Tensor
    stats: UpdateStats


@dataclass(frozen=True, kw_only=True)
class AgentUpdate:
    """One agent's accepted answer to a round's train request, as the server holds it."""

    agent_index: int
    agent_id: str
    theta: torch.Tensor
    """θ_k, a flat float32 vector."""
    stats: UpdateStats

    def to_json(self) -> dict[str, Any]:
        row = self.stats.to_json()
        row["id"], row["index"] = self.agent_id, self.agent_index
        return row


@dataclass(frozen=True, kw_only=True)
class SavedState:
    """What a stateful part (a server strategy, an optimizer) hands a checkpoint, and takes back
    on resume: JSON-like scalars and named float arrays (stored as raw bytes, never pickled)."""

    scalars: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
