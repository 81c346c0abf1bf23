"""The run's estimator on a batch of trajectories: the torch definition every backend is held
to (``common/learning/estimators.py`` holds the maths; this applies it to a batch's cells)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.learning import estimators
from fedhpg.common.learning.engine.trajectories import Trajectories


@dataclass(frozen=True)
class EstimatorOptions:
    """The estimator's settings (``algo.estimator``, ``baseline``, ``reward_to_go``,
    ``normalize``)."""

    estimator: estimators.EstimatorName = "gpomdp"
    baseline: estimators.BaselineName = "mean"
    reward_to_go: estimators.RewardToGoName = "from_start"
    normalize: estimators.NormalizeName = "none"

    @classmethod
    def of(cls, algo: AlgoConfig) -> EstimatorOptions:
        return cls(
            estimator=algo.estimator,
            baseline=algo.baseline,
            reward_to_go=algo.reward_to_go,  # type: ignore[arg-type]
            normalize=algo.normalize,  # type: ignore[arg-type]
        )


def batch_coefficients(
    batch: Trajectories,
    options: EstimatorOptions,
    gammas: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """The estimator's coefficients of ``batch``, one per cell of ``batch.layout``, [S]
    float64: each row's trajectories its baselines' group, discounted by its γ (``gammas``
    [A]); ``weights``: importance weights, [N] per trajectory or [T, N] per decision."""
    layout = batch.layout
    rewards, alive = batch.cells
    if weights is not None and weights.dim() == 2:
        weights = layout.gather(weights)
    return estimators.coefficients(
        options.estimator,
        layout,
        rewards,
        alive,
        gamma=gammas[batch.owner],
        baseline=options.baseline,
        weights=weights,
        reward_to_go=options.reward_to_go,
        normalize=options.normalize,
        groups=batch.owner,
    )
