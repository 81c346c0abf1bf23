"""A group's round column-wise: its :class:`~fedhpg.common.records.types.RoundResult` (every agent's
θ_k as a row of one [A, d] array, every field of their statistics as one column) and every
local iteration's work (what the device emulation prices) as arrays over the agents that ran
it. An agent host of many agents would spend more time on per-agent objects than on its
engine if it built one per agent and iteration; a lone agent takes the same shape, one row.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from fedhpg.common.records.types import RoundResult


@dataclass(frozen=True)
class IterationColumns:
    """One local iteration of the round's agents at ``positions`` (rows of the round)."""

    positions: np.ndarray
    """int64 rows of the round's result that ran this iteration."""
    compute_s: np.ndarray
    """float64 thread CPU seconds each one's iteration took here."""
    env_steps: np.ndarray
    """int64."""
    grad_steps: np.ndarray
    """int64 trajectory steps differentiated."""


@dataclass(frozen=True)
class TrainedRound:
    """A group's round of ``result.agents``: the :class:`RoundResult` (its statistics'
    device columns at their defaults) and every local iteration's work, which the caller's
    device emulation prices into those columns."""

    result: RoundResult
    iterations: list[IterationColumns] = field(default_factory=list)
    """In the order they ran; an agent's own iterations in its order."""

    @staticmethod
    def concatenated(parts: Sequence[TrainedRound]) -> TrainedRound:
        """The rounds of groups of distinct agents as one (rows in agent order), each
        iteration's positions moved to its agents' rows there."""
        if len(parts) == 1:
            return parts[0]
        whole = RoundResult.concatenated([part.result for part in parts])
        place = {k: i for i, k in enumerate(whole.agents)}
        iterations = []
        for part in parts:
            moved = np.array([place[k] for k in part.result.agents], dtype=np.int64)
            iterations += [
                dataclasses.replace(ran, positions=moved[ran.positions]) for ran in part.iterations
            ]
        return TrainedRound(result=whole, iterations=iterations)
