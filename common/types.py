"""One agent's work in one round, typed end to end.

The algorithm returns a :class:`LocalResult` (θ_k and :class:`UpdateStats`); the host that
emulates the agent's device fills in the device fields; the stats cross the wire unchanged in
``Update.stats`` (the codec checks every field against these annotations); the server holds an
:class:`AgentUpdate` per agent, which strategies aggregate and ``metrics.jsonl`` records. An
evaluation travels as :class:`EvaluationStats`. torch is imported for type checking only.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    import torch


@dataclass(frozen=True, kw_only=True)
class UpdateStats:
    """What one round's local update cost and measured (``metrics.jsonl``'s ``agents[]``)."""

    trajectories: int
    """Trajectories sampled this round (B_k·τ_k for FedHPG, B_k + N·b_k for FedHPGVR)."""
    env_steps: int
    """Environment steps of those trajectories (steps after an episode's end not counted)."""
    compute_s: float
    """CPU time of the local update on the agent's thread (sampling, estimation, steps)."""
    train_return: float
    """Mean undiscounted return of the round's training trajectories."""
    grad_clipped: int = 0
    """Local steps whose gradient was clipped to ``algo.grad_clip``."""
    emulated_s: float = 0.0
    """Emulated device time: compute_s / speed + env_steps × step_delay_s (+ latency)."""
    speed: float = 1.0
    """The device speed during the round (after the schedule)."""
    local_wall_s: float | None = None
    """Wall time the agent process spent on the round, sleeps included (distributed only)."""
    algorithm: dict[str, float] = field(default_factory=dict)
    """The algorithm's own per-round statistics (FedHPGVR: ``iw_mean``, ``iw_max``, ...)."""

    def problems(self) -> list[str]:
        """What makes these stats unusable: non-finite or negative numbers."""
        found = []
        for name in ("trajectories", "env_steps", "grad_clipped"):
            if getattr(self, name) < 0:
                found.append(f"{name} is negative")
        numbers = {
            "compute_s": self.compute_s,
            "train_return": self.train_return,
            "emulated_s": self.emulated_s,
            "speed": self.speed,
            **({"local_wall_s": self.local_wall_s} if self.local_wall_s is not None else {}),
            **{f"algorithm[{k!r}]": v for k, v in self.algorithm.items()},
        }
        found += [f"{name} is not finite" for name, v in numbers.items() if not math.isfinite(v)]
        return found

    def to_json(self) -> dict[str, Any]:
        """The flat ``agents[]`` entry of metrics.jsonl (schema 1): algorithm stats inline,
        ``local_wall_s`` only where it was measured."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        algorithm = values.pop("algorithm")
        if values["local_wall_s"] is None:
            del values["local_wall_s"]
        return {**values, **{name: float(value) for name, value in algorithm.items()}}


@dataclass(frozen=True, kw_only=True)
class EvaluationStats:
    """The unified policy's performance over ``episodes`` episodes in one agent's environment."""

    return_mean: float
    return_std: float
    discounted_return_mean: float
    """Mean return discounted with that agent's γ_k."""
    success_rate: float
    """Fraction of episodes that reached the goal (0 where the env has no goal)."""
    length_mean: float
    episodes: int

    def problems(self) -> list[str]:
        numbers = dataclasses.asdict(self)
        found = [f"{name} is not finite" for name, v in numbers.items() if not math.isfinite(v)]
        if not 0.0 <= self.success_rate <= 1.0:
            found.append("success_rate is outside [0, 1]")
        if self.episodes < 1:
            found.append("episodes < 1")
        return found

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
        return {**self.stats.to_json(), "id": self.agent_id, "index": self.agent_index}


@dataclass(frozen=True, kw_only=True)
class SavedState:
    """What a stateful part (a server strategy, an optimizer) hands a checkpoint, and takes back
    on resume: JSON-like scalars and named float arrays (stored as raw bytes, never pickled)."""

    scalars: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
