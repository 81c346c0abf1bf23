"""A plugin as a user would write one, outside the package: one algorithm, one strategy.

Imported by name (``plugins=[fedhpg_toy_plugin]``); nothing in fedhpg knows of it.

- ``toy_sign``: each local iteration steps θ by ``scale`` · sign(batch gradient) (signSGD), on
  ``budget.batch_size`` trajectories, ``budget.steps`` times; it reports the fraction of
  coordinates whose sign flipped between the first and the last step. Written with the
  engine's primitives over rows of agents, it runs batched like the built-in algorithms.
- ``toy_alternate``: odd rounds ask every agent, even rounds only the even-indexed ones;
  θ̃ is the plain mean of whoever answered.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from fedhpg.common.configuration.registry import OptionError
from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.learning.algorithms import Algorithm, at_least_one, register_algorithm
from fedhpg.common.learning.engine.round import Round
from fedhpg.server.strategies import CoordinateRule, NoParams, register_strategy


@dataclass(frozen=True, kw_only=True)
class ToySignParams:
    scale: float = 0.01

    def __post_init__(self) -> None:
        if self.scale <= 0:
            raise OptionError("scale", f"got {self.scale!r}, must be > 0")


@dataclass(frozen=True, kw_only=True)
class ToySignBudget:
    batch_size: int = 4
    steps: int = 1

    def __post_init__(self) -> None:
        at_least_one("batch_size", self.batch_size)
        at_least_one("steps", self.steps)


@register_algorithm
class ToySign(Algorithm[ToySignParams, ToySignBudget]):
    name = "toy_sign"
    Params = ToySignParams
    Budget = ToySignBudget

    def local_update(
        self, rows: Round, settings: AlgoConfig, params: ToySignParams
    ) -> torch.Tensor:
        theta = rows.theta.clone()
        steps, batch_size = rows.budget("steps"), rows.budget("batch_size")
        signs = []
        for step in range(int(steps.max())):
            active = steps > step
            batch = rows.sample(theta, torch.where(active, batch_size, 0), iteration=step)
            signs.append(torch.sign(rows.mean_gradients(theta, batch)))
            theta += params.scale * signs[-1] * active.unsqueeze(1)
            rows.finished(batch)
        flipped = (signs[0] != signs[-1]).double().mean(dim=1)
        rows.report("sign_flips", flipped)
        return theta


@register_strategy
class ToyAlternate(CoordinateRule[NoParams]):
    name = "toy_alternate"

    def select(self, round_index: int, agents: Sequence[int]) -> list[int]:
        return list(agents) if round_index % 2 else [k for k in agents if k % 2 == 0]

    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        return rows.mean(dim=0)
