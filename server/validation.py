"""The checks every update passes before a strategy sees it, the same in every pool."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fedhpg.common.types import UpdateStats

NON_FINITE = "parameters contain NaN or Inf"


@dataclass(frozen=True, kw_only=True)
class UpdateCheck:
    """θ_k must be a finite float32 vector of the run's size, within ``max_update_norm`` of the
    round's θ̃ (when set), with finite, non-negative statistics."""

    num_params: int
    max_update_norm: float | None = None

    def _layout_problem(self, dtype: np.dtype, shape: tuple[int, ...]) -> str | None:
        if dtype != np.float32:
            return f"parameters must be float32, got {dtype}"
        if shape != (self.num_params,):
            return f"parameters must have shape ({self.num_params},), got {shape}"
        return None

    def theta_problem(self, theta: np.ndarray) -> str | None:
        problem = self._layout_problem(theta.dtype, theta.shape)
        if problem is None and not np.isfinite(theta).all():
            return NON_FINITE
        return problem

    def _step_problem(self, step: float) -> str | None:
        bound = self.max_update_norm
        if bound is not None and step > bound:
            return f"update moves θ by {step:.4g} > server.max_update_norm={bound:g}"
        return None

    def problem(
        self,
        theta: np.ndarray,
        stats: UpdateStats,
        broadcast: np.ndarray | None,
        *,
        stats_bounded: bool = False,
    ) -> str | None:
        """Why the update cannot be aggregated, or None. ``broadcast`` is the round's θ̃
        (None when the update is for another round: the bound is then not checked).
        ``stats_bounded``: the stats came through the codec, which enforced these very bounds
        on every field (the zmq pool's case: not checked twice, ~5 µs per agent)."""
        problem = self.theta_problem(theta)
        if problem is not None:
            return problem
        problems = [] if stats_bounded else stats.problems()
        if problems:
            return "update stats: " + "; ".join(problems)
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
    ) -> list[str | None]:
        """:meth:`problem` of each row of the [A, d] matrix ``thetas`` (with ``stats[i]``),
        the same answer row by row, but each pass over the matrix made once for all rows: at
        d = 10⁴ a host's batch of 256 rows is 10 MB, and per-row numpy calls cost more than
        the arithmetic."""
        rows = len(thetas)
        layout = self._layout_problem(thetas.dtype, thetas.shape[1:])
        if layout is not None:
            return [layout] * rows
        result: list[str | None] = [None] * rows
        # A row's sum is finite only if every entry is (NaN and ±Inf propagate); a sum that
        # overflowed from finite entries is told apart by the exact test, row by row.
        with np.errstate(over="ignore", invalid="ignore"):  # inf + -inf, overflow: expected
            sums = np.add.reduce(thetas, axis=1)
        for row in np.flatnonzero(~np.isfinite(sums)).tolist():
            if not np.isfinite(thetas[row]).all():
                result[row] = NON_FINITE
        if not stats_bounded:
            for i, row_stats in enumerate(stats):
                if result[i] is None and (found := row_stats.problems()):
                    result[i] = "update stats: " + "; ".join(found)
        if self.max_update_norm is not None and broadcast is not None:
            checked = [i for i in range(rows) if result[i] is None]
            kept = thetas if len(checked) == rows else thetas[checked]
            # one float64 pass for the rows; each norm as np.linalg.norm computes a vector's
            # (the square root of its dot product with itself), so a bound decides alike
            steps = kept.astype(np.float64) - broadcast
            for i, step in zip(checked, steps, strict=True):
                result[i] = self._step_problem(math.sqrt(float(step.dot(step))))
        return result
