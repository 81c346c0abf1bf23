"""The checks every update passes before a strategy sees it, the same in every pool."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fedhpg.common.types import UpdateStats


@dataclass(frozen=True, kw_only=True)
class UpdateCheck:
    """θ_k must be a finite float32 vector of the run's size, within ``max_update_norm`` of the
    round's θ̃ (when set), with finite, non-negative statistics."""

    num_params: int
    max_update_norm: float | None = None

    def theta_problem(self, theta: np.ndarray) -> str | None:
        if theta.dtype != np.float32:
            return f"parameters must be float32, got {theta.dtype}"
        if theta.shape != (self.num_params,):
            return f"parameters must have shape ({self.num_params},), got {theta.shape}"
        if not np.isfinite(theta).all():
            return "parameters contain NaN or Inf"
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
        bound = self.max_update_norm
        if bound is not None and broadcast is not None:
            step = float(np.linalg.norm(theta.astype(np.float64) - broadcast))
            if step > bound:
                return f"update moves θ by {step:.4g} > server.max_update_norm={bound:g}"
        return None
