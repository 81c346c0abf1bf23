"""FedPG-BR's agent half (Fan et al., NeurIPS 2021, Algorithm 1 lines 3-5): one gradient.

Each round t every agent samples B_t trajectories at the server's θ̃_0^t and sends its GPOMDP
gradient μ_t^(k). fedhpg agents send parameter vectors, so the agent sends θ_k = θ̃ + μ_t^(k)
and the server reads μ_t^(k) = θ_k − θ̃ (an attack on "the gradient", common/learning/attacks.py,
then acts on exactly FedPG-BR's μ). The Byzantine filter and the SCSG inner loop are the server's:
:mod:`fedhpg.server.strategies.fedpgbr`.

B_t is drawn uniformly from [batch_min, batch_max] (both included, as FedPG-BR's code draws it)
and N_t ~ Geom(b / (B_t + b)) on {1, 2, …} (its code's draw: mean (B_t + b)/b), both from the
(seed, round) stream :func:`round_schedule`, so agents and server agree without a message.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import OptionError
from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.configuration.vocabularies import ESTIMATORS
from fedhpg.common.learning.algorithms import GRADIENTS, Algorithm, register_algorithm
from fedhpg.common.learning.engine.round import Round

SCHEDULE_KEY = 0x46504252
"""Third word of the (seed, round, key) seed of a round's B_t and N_t: no agent stream
[seed, agent, round, purpose] has a round index this large, so the streams never meet."""


@dataclass(frozen=True, kw_only=True)
class FedPGBRParams:
    """FedPG-BR's batch sizes (``algo.params``); its CartPole values are the defaults."""

    batch_min: int = 14
    """B_min: the smallest B_t, the trajectories each agent samples in a round."""
    batch_max: int = 18
    """B_max: the largest B_t (included)."""
    mini_batch_size: int = 4
    """b: trajectories per SCSG inner step, sampled by the server."""

    def __post_init__(self) -> None:
        for name in ("batch_min", "batch_max", "mini_batch_size"):
            if getattr(self, name) < 1:
                raise OptionError(name, f"got {getattr(self, name)!r}, must be an integer >= 1")
        if self.batch_max < self.batch_min:
            raise OptionError(
                "batch_max", f"got {self.batch_max}, below batch_min = {self.batch_min}"
            )


@dataclass(frozen=True, kw_only=True)
class FedPGBRBudget:
    """FedPG-BR gives every agent the round's B_t (``algo.params``): no per-agent budget."""


@dataclass(frozen=True)
class RoundSchedule:
    batch_size: int
    """B_t."""
    inner_steps: int
    """N_t."""


def round_schedule(seed: int, round_index: int, params: FedPGBRParams) -> RoundSchedule:
    """B_t ~ U{B_min … B_max}, then N_t ~ Geom(b / (B_t + b)), from the (seed, round) stream."""
    rng = np.random.default_rng([seed, round_index, SCHEDULE_KEY])
    batch = int(rng.integers(params.batch_min, params.batch_max + 1))
    steps = int(rng.geometric(params.mini_batch_size / (batch + params.mini_batch_size)))
    return RoundSchedule(batch_size=batch, inner_steps=steps)


@register_algorithm
class FedPGBR(Algorithm[FedPGBRParams, FedPGBRBudget]):
    """Send θ̃ + μ, μ the GPOMDP gradient of B_t trajectories at θ̃ (strategy=fedpgbr)."""

    name = "fedpgbr"
    Params = FedPGBRParams
    Budget = FedPGBRBudget
    strategy = "fedpgbr"
    sends = GRADIENTS

    def local_update(
        self, rows: Round, settings: AlgoConfig, params: FedPGBRParams
    ) -> torch.Tensor:
        size = round_schedule(rows.seed, rows.round_index, params).batch_size
        batch = rows.sample(rows.theta, torch.full((rows.size,), size), iteration=0)
        mu = rows.mean_gradients(rows.theta, batch)
        rows.finished(batch)
        return rows.theta + mu

    def check(self, settings: AlgoConfig, params: FedPGBRParams) -> None:
        if not ESTIMATORS.get(settings.estimator).per_step:
            raise ConfigError(
                "algo.estimator",
                f"FedPG-BR's gradients are GPOMDP's, got {settings.estimator!r}: set "
                "algo.estimator=gpomdp",
            )

    def describe_budget(self, budget: FedPGBRBudget) -> str:
        return "B_t from algo.params"
