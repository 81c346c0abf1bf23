"""The checks every update passes before a strategy sees it, the same in every pool.

A rejected update comes with a :class:`Rejection`: a code that the round loop acts on (every
update non-finite: the local steps diverged) and a reason for people (logs, ``metrics.jsonl``'s
``failures``, the ``Error`` sent back to the agent).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

from fedhpg.common.records.types import UpdateStats

NON_FINITE = "parameters contain NaN or Inf"
"""The reason of a :attr:`Reject.NON_FINITE` rejection."""


class Reject(StrEnum):
    """Why an update was not aggregated (the kind; :class:`Rejection` says more)."""

    LAYOUT = "layout"
    """θ_k is not a float32 vector of the run's size."""
    NON_FINITE = "non_finite"
    """θ_k holds NaN or ±Inf."""
    STATS = "stats"
    """The statistics break their bounds."""
    TOO_FAR = "too_far"
    """θ_k is farther from θ̃ than ``server.max_update_norm``."""
    PROTOCOL = "protocol"
    """A secure round's message the protocol refused: its agent dropped out of the round."""
    UNKNOWN = "unknown"
    """Read back from a checkpoint that kept only the reason."""


@dataclass(frozen=True)
class Rejection:
    """A rejected update: what kind of fault (:attr:`code`) and, in words, why."""

    code: Reject
    reason: str

    def __str__(self) -> str:
        return self.reason

    def saved(self) -> dict[str, str]:
        return {"code": str(self.code), "reason": self.reason}

    @classmethod
    def restore(cls, saved: Any) -> Rejection:
        """What :meth:`saved` wrote (a plain reason: of unknown kind)."""
        if isinstance(saved, Mapping):
            return cls(Reject(saved["code"]), str(saved["reason"]))
        return cls(Reject.UNKNOWN, str(saved))


def diverged(failures: Mapping[str, Rejection]) -> bool:
    """Whether every rejected update was non-finite (and there was one): the local steps
    themselves blew up, not one bad agent."""
    return bool(failures) and all(r.code is Reject.NON_FINITE for r in failures.values())


def reasons(failures: Mapping[str, Rejection]) -> dict[str, str]:
    """Agent id → why, in words (what strategies and ``metrics.jsonl`` take)."""
    return {agent: r.reason for agent, r in failures.items()}


@dataclass(frozen=True, kw_only=True)
class UpdateCheck:
    """θ_k must be a finite float32 vector of the run's size, within ``max_update_norm`` of the
    round's θ̃ (when set), with finite, non-negative statistics."""

    num_params: int
    max_update_norm: float | None = None

    def _layout_problem(self, dtype: np.dtype, shape: tuple[int, ...]) -> Rejection | None:
        if dtype != np.float32:
            return Rejection(Reject.LAYOUT, f"parameters must be float32, got {dtype}")
        if shape != (self.num_params,):
            return Rejection(
                Reject.LAYOUT, f"parameters must have shape ({self.num_params},), got {shape}"
            )
        return None

    def theta_problem(self, theta: np.ndarray) -> Rejection | None:
        problem = self._layout_problem(theta.dtype, theta.shape)
        if problem is None and not np.isfinite(theta).all():
            return _NON_FINITE
        return problem

    def _step_problem(self, step: float) -> Rejection | None:
        bound = self.max_update_norm
        if bound is not None and step > bound:
            return Rejection(
                Reject.TOO_FAR,
                f"update moves θ by {step:.4g} > server.max_update_norm={bound:g}",
            )
        return None

    def problem(
        self,
        theta: np.ndarray,
        stats: UpdateStats,
        broadcast: np.ndarray | None,
        *,
        stats_bounded: bool = False,
    ) -> Rejection | None:
        """Why the update cannot be aggregated, or None. ``broadcast`` is the round's θ̃
        (None when the update is for another round: the bound is then not checked).
        ``stats_bounded``: the stats came through the codec, which enforced these very bounds
        on every field (the zmq pool's case: not checked twice, a cost per agent)."""
        problem = self.theta_problem(theta)
        if problem is not None:
            return problem
        problems = [] if stats_bounded else stats.problems()
        if problems:
            return _stats_problem(problems)
        if self.max_update_norm is not None and broadcast is not None:
            return self._step_problem(float(np.linalg.norm(theta.astype(np.float64) - broadcast)))
        return None

    def problems(
        self,
        thetas: np.ndarray,
        stats: Sequence[UpdateStats],
        broadcast: np.ndarray | None,
        *,
        stats_bounded: bool = False,
    ) -> list[Rejection | None]:
        """:meth:`problem` of each row of the [A, d] matrix ``thetas`` (with ``stats[i]``),
        the same answer row by row, but each pass over the matrix made once for all rows: at
        d = 10⁴ a host's batch of 256 rows is 10 MB, and per-row numpy calls cost more than
        the arithmetic."""
        rows = len(thetas)
        layout = self._layout_problem(thetas.dtype, thetas.shape[1:])
        if layout is not None:
            return [layout] * rows
        result: list[Rejection | None] = [None] * rows
        # A row's sum is finite only if every entry is (NaN and ±Inf propagate); a sum that
        # overflowed from finite entries is told apart by the exact test, row by row.
        with np.errstate(over="ignore", invalid="ignore"):  # inf + -inf, overflow: expected
            sums = np.add.reduce(thetas, axis=1)
        for row in np.flatnonzero(~np.isfinite(sums)).tolist():
            if not np.isfinite(thetas[row]).all():
                result[row] = _NON_FINITE
        if not stats_bounded:
            for i, row_stats in enumerate(stats):
                if result[i] is None and (found := row_stats.problems()):
                    result[i] = _stats_problem(found)
        if self.max_update_norm is not None and broadcast is not None:
            checked = [i for i in range(rows) if result[i] is None]
            kept = thetas if len(checked) == rows else thetas[checked]
            # one float64 pass for the rows; each norm as np.linalg.norm computes a vector's
            # (the square root of its dot product with itself), so a bound decides alike
            steps = kept.astype(np.float64) - broadcast
            for i, step in zip(checked, steps, strict=True):
                result[i] = self._step_problem(math.sqrt(float(step.dot(step))))
        return result


_NON_FINITE = Rejection(Reject.NON_FINITE, NON_FINITE)


def _stats_problem(problems: list[str]) -> Rejection:
    return Rejection(Reject.STATS, "update stats: " + "; ".join(problems))
