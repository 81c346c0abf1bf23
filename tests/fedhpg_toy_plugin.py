"""A plugin as a user would write one, outside the package: one algorithm, one strategy.

Imported by name (``plugins=[fedhpg_toy_plugin]``); nothing in fedhpg knows of it.

- ``toy_sign``: each local iteration steps θ by ``scale`` · sign(batch gradient) (signSGD), on
  ``budget.batch_size`` trajectories, ``budget.steps`` times; it reports the fraction of
  coordinates whose sign flipped between the first and the last step.
- ``toy_alternate``: odd rounds ask every agent, even rounds only the even-indexed ones;
  θ̃ is the plain mean of whoever answered.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from fedhpg.common.algorithms import Algorithm, LocalContext, at_least_one, register_algorithm
from fedhpg.common.local import LocalTally, batch_gradient
from fedhpg.common.policies import get_flat_params, set_flat_params
from fedhpg.common.registry import OptionError
from fedhpg.common.types import LocalResult
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
        self,
        theta: torch.Tensor,
        context: LocalContext,
        params: ToySignParams,
        budget: ToySignBudget,
    ) -> LocalResult:
        set_flat_params(context.policy, theta)
        tally = LocalTally()
        signs = []
        for step in range(budget.steps):
            started = time.thread_time()
            batch = context.sample(budget.batch_size)
            gradient = batch_gradient(
                context.policy, batch, algo=context.settings, gamma=context.gamma
            )
            signs.append(torch.sign(gradient))
            set_flat_params(
                context.policy, get_flat_params(context.policy) + params.scale * signs[-1]
            )
            compute_s = time.thread_time() - started
            tally.add(batch, compute_s=compute_s)
            if context.on_iteration is not None:
                context.on_iteration(step, compute_s, batch.num_steps)
        tally.algorithm["sign_flips"] = float((signs[0] != signs[-1]).float().mean())
        return tally.result(get_flat_params(context.policy))


@register_strategy
class ToyAlternate(CoordinateRule[NoParams]):
    name = "toy_alternate"

    def select(self, round_index: int, agents: Sequence[int]) -> list[int]:
        return list(agents) if round_index % 2 else [k for k in agents if k % 2 == 0]

    def combine(self, rows: torch.Tensor) -> torch.Tensor:
        return rows.mean(dim=0)
