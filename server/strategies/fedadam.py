"""``fedadam``: Adam on the pseudo-gradient another strategy defines (FedOpt, Reddi et al. 2021).

θ̄ = inner.aggregate(θ̃, updates)       (``inner``: mean by default; median, trimmed_mean, ...)
θ̃ ← θ̃ + Adam(θ̄ − θ̃)

With local plain steps of size 1 and τ_k = 1, θ̄ − θ̃ is the average gradient and this is the
server of FedPG-BR's experiments. The Adam moments persist across rounds: checkpoints keep them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from fedhpg.common.configuration.registry import OptionError
from fedhpg.common.configuration.settings.strategy import StrategyConfig
from fedhpg.common.learning.optim import AdamAscent
from fedhpg.common.records.types import RoundResult, SavedState
from fedhpg.server.strategies import Strategy, make_strategy, register_strategy

INNER = "inner."


@dataclass(frozen=True, kw_only=True)
class FedAdamParams:
    step_size: float = 1e-3
    """Adam's step size on the server."""
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    inner: str = "mean"
    """The strategy whose aggregate defines the pseudo-gradient."""
    inner_params: dict[str, Any] = field(default_factory=dict)
    """That strategy's options (e.g. ``{trim_fraction: 0.3}``)."""

    def __post_init__(self) -> None:
        if self.step_size <= 0:
            raise OptionError("step_size", f"got {self.step_size!r}, must be > 0")
        for name in ("beta1", "beta2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise OptionError(name, f"got {getattr(self, name)!r}, must be in [0, 1)")
        if self.eps <= 0:
            raise OptionError("eps", f"got {self.eps!r}, must be > 0")
        if self.inner == "fedadam":
            raise OptionError("inner", "fedadam cannot wrap itself")


@register_strategy
class FedAdam(Strategy[FedAdamParams]):
    """Server-side Adam over an inner aggregation rule."""

    name = "fedadam"
    Params = FedAdamParams

    def __init__(self, params: FedAdamParams) -> None:
        super().__init__(params)
        self.inner = make_strategy(
            StrategyConfig(name=params.inner, params=dict(params.inner_params)),
            key="strategy.params.inner",
        )
        self.adam = AdamAscent(params.step_size, betas=(params.beta1, params.beta2), eps=params.eps)

    def select(self, round_index: int, agents: Sequence[int]) -> list[int]:
        return self.inner.select(round_index, agents)

    def tolerance(self, rows: int) -> int | None:
        return self.inner.tolerance(rows)

    def round_stats(self) -> dict[str, Any]:
        return self.inner.round_stats()

    def averaging(self) -> str | None:
        return self.inner.averaging()

    def from_average(
        self, round_index: int, theta: torch.Tensor, average: torch.Tensor
    ) -> torch.Tensor:
        return theta + self.adam.direction(average - theta)

    def sampled_trajectories(self) -> int:
        return self.inner.sampled_trajectories()

    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        result: RoundResult,
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        target = self.inner.aggregate(round_index, theta, result, failures)
        return self.from_average(round_index, theta, target)

    def state(self) -> SavedState:
        own, inner = self.adam.state(), self.inner.state()
        return SavedState(
            scalars={**own.scalars, "inner": inner.scalars},
            arrays={**own.arrays, **{INNER + k: v for k, v in inner.arrays.items()}},
        )

    def restore(self, state: SavedState) -> None:
        scalars = dict(state.scalars)
        inner_scalars = scalars.pop("inner", {})
        own = {k: v for k, v in state.arrays.items() if not k.startswith(INNER)}
        inner = {k[len(INNER) :]: v for k, v in state.arrays.items() if k.startswith(INNER)}
        self.adam.restore(SavedState(scalars=scalars, arrays=own))
        self.inner.restore(SavedState(scalars=inner_scalars, arrays=inner))
