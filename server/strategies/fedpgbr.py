"""``fedpgbr``: FedPG-BR's server (Fan et al., NeurIPS 2021, Algorithm 1 lines 6-13).

Each round t, from the agents' gradients μ_t^(k) = θ_k − θ̃_0^t (``algo=fedpgbr``):

μ_t = mean of the gradients the Byzantine filter keeps  (common/learning/byzantine_filter.py)
for n = 0 … N_t − 1:                                     (SCSG, N_t ~ Geom(b / (B_t + b)))
    v_n = (1/b) Σ_j [g(τ_j|θ_n) − ω_j g(τ_j|θ_0)] + μ_t,   τ_j ~ p(·|θ_n), b of them
    θ_{n+1} = θ_n + Adam_η(v_n)
θ̃_0^{t+1} = θ_{N_t}

The b inner trajectories come from the server's own copy of agent ``server_env_agent``'s
environment variant (agent 0's by default: the federation's agents all share it in a
homogeneous run), sampled on the engine as a batch of one row, from keys of their own (the
server's purpose, the round, the inner step), so a run is reproducible and a resumed run
continues bit for bit. ω_j = p(τ_j|θ_0) / p(τ_j|θ_n) (FedHPGVR's weights,
:mod:`fedhpg.common.learning.algorithms.fedhpgvr`). The step is Adam, as in FedPG-BR's code; its
moments persist across rounds and checkpoints keep them. Where the filter keeps no gradient,
the round's inner steps are plain GPOMDP steps on the server's samples (FedPG-BR's code does
the same).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import OptionError, parse_options
from fedhpg.common.heterogeneity.variants import variant_of
from fedhpg.common.learning.algorithms import GRADIENTS
from fedhpg.common.learning.algorithms.fedhpgvr import FedHPGVRParams, semi_stochastic_gradient
from fedhpg.common.learning.algorithms.fedpgbr import FedPGBRParams, round_schedule
from fedhpg.common.learning.byzantine_filter import byzantine_filter
from fedhpg.common.learning.engine.engine import Engine, engine_settings
from fedhpg.common.learning.optim import AdamAscent
from fedhpg.common.learning.randomness import Purpose
from fedhpg.common.records.types import RoundResult, SavedState
from fedhpg.server.strategies import Strategy, register_strategy, rows_of

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class FedPGBRStrategyParams:
    """FedPG-BR's filter and server step (``strategy.params``); B_t and b are ``algo.params``."""

    step_size: float = 1e-3
    """η: Adam's step size on the server's inner steps."""
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    sigma: float | None = None
    """σ, the bound on a single trajectory's gradient deviation (E‖g − ∇J‖² ≤ σ²) the filter's
    thresholds scale with; null = set each round from the agents' gradients so that rule 1's
    threshold is ``margin`` × the distance between two honest ones (a departure from the
    paper, which assumes σ known: common/learning/byzantine_filter.py, estimated_sigma)."""
    margin: float = 1.5
    """With sigma null: rule 1's threshold over the median honest distance (> 1)."""
    delta: float = 0.6
    """δ: the filter's confidence, V = 2 log(2K/δ) (FedPG-BR's CartPole value)."""
    alpha: float = 0.4
    """α: the largest fraction of Byzantine agents assumed (< 0.5); rule 1 must keep at least
    (1 − α)K gradients, else rule 2 decides."""
    server_env_agent: int = 0
    """Whose environment variant the server samples its inner-loop trajectories from."""
    iw_mode: Literal["trajectory", "per_decision"] = "trajectory"
    """ω per trajectory (FedPG-BR) or per decision (FedHPGVR's default with GPOMDP)."""

    def __post_init__(self) -> None:
        if self.step_size <= 0:
            raise OptionError("step_size", f"got {self.step_size!r}, must be > 0")
        for name in ("beta1", "beta2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise OptionError(name, f"got {getattr(self, name)!r}, must be in [0, 1)")
        if self.eps <= 0:
            raise OptionError("eps", f"got {self.eps!r}, must be > 0")
        if self.sigma is not None and self.sigma <= 0:
            raise OptionError("sigma", f"got {self.sigma!r}, must be > 0 (or null: estimated)")
        if self.margin <= 1.0:
            raise OptionError("margin", f"got {self.margin!r}, must be > 1")
        if not 0.0 < self.delta < 1.0:
            raise OptionError("delta", f"got {self.delta!r}, must be in (0, 1)")
        if not 0.0 <= self.alpha < 0.5:
            raise OptionError("alpha", f"got {self.alpha!r}, must be in [0, 0.5)")
        if self.server_env_agent < 0:
            raise OptionError("server_env_agent", f"got {self.server_env_agent!r}, must be >= 0")


@dataclass
class _ServerSide:
    """What the inner loop samples and differentiates with (built by :meth:`FedPGBR.bind`)."""

    run: RunConfig
    schedule: FedPGBRParams
    engine: Engine
    """The engine of one row: agent ``server_env_agent``'s variant."""
    agent: int


@register_strategy
class FedPGBR(Strategy[FedPGBRStrategyParams]):
    """The Byzantine filter on the agents' gradients, then N_t SCSG steps on the server."""

    name = "fedpgbr"
    Params = FedPGBRStrategyParams
    takes = GRADIENTS
    """μ_t^(k) = θ_k − θ̃_0^t, sent as θ̃ + μ by ``algo=fedpgbr``."""
    buffered = False
    """The filter and the SCSG loop need every agent's gradient at one θ̃ each round."""

    def __init__(self, params: FedPGBRStrategyParams) -> None:
        super().__init__(params)
        self.adam = AdamAscent(params.step_size, betas=(params.beta1, params.beta2), eps=params.eps)
        self.side: _ServerSide | None = None
        self.stats: dict[str, Any] = {}

    def bind(self, run: RunConfig) -> None:
        if self.params.server_env_agent >= run.agents.num_agents:
            raise ConfigError(
                "strategy.params.server_env_agent",
                f"got {self.params.server_env_agent}, but the run has "
                f"{run.agents.num_agents} agents (0 … {run.agents.num_agents - 1})",
            )
        schedule = parse_options(FedPGBRParams, run.algo.params, "algo.params")
        agent = self.params.server_env_agent
        self.side = _ServerSide(
            run=run,
            schedule=schedule,
            engine=Engine(run, {agent: variant_of(run, agent)}),
            agent=agent,
        )

    def aggregate(
        self,
        round_index: int,
        theta: torch.Tensor,
        result: RoundResult,
        failures: Mapping[str, str],
    ) -> torch.Tensor:
        side = self.side
        if side is None:
            raise RuntimeError("the fedpgbr strategy was not bound to its run (bind(run))")
        plan = round_schedule(side.run.seed, round_index, side.schedule)
        gradients = rows_of(result) - theta
        found = byzantine_filter(
            gradients,
            batch_size=plan.batch_size,
            sigma=self.params.sigma,
            delta=self.params.delta,
            alpha=self.params.alpha,
            margin=self.params.margin,
        )
        order = result.agents
        kept = [order[i] for i in found.kept]
        if not kept:
            logger.warning("round %d: the Byzantine filter kept no gradient", round_index)
        mu = gradients[found.kept].mean(dim=0) if kept else None
        with engine_settings(side.engine.device):
            theta_n = self._inner_loop(round_index, theta, mu, plan.inner_steps, side)
        self.stats = {
            "batch_size": plan.batch_size,
            "inner_steps": plan.inner_steps,
            "trajectories": plan.inner_steps * side.schedule.mini_batch_size,
            "kept": kept,
            "rejected": [k for k in order if k not in kept],
            "rule": found.rule,
            "threshold": found.threshold,
            "sigma": found.sigma,
        }
        return theta_n

    def _inner_loop(
        self,
        round_index: int,
        theta: torch.Tensor,
        mu: torch.Tensor | None,
        steps: int,
        side: _ServerSide,
    ) -> torch.Tensor:
        """N_t SCSG steps from θ̃_0 = ``theta`` on b trajectories each (Adam on v_n)."""
        engine = side.engine
        rows = engine.begin(round_index, theta, [side.agent])
        snapshot = rows.theta
        current = snapshot.clone()
        weights = FedHPGVRParams(iw_mode=self.params.iw_mode)
        size = torch.tensor([side.schedule.mini_batch_size])
        for step in range(steps):
            batch = rows.sample(current, size, iteration=step, purpose=Purpose.SERVER)
            if mu is None:  # no kept gradient: a plain GPOMDP step on the server's samples
                direction = rows.mean_gradients(current, batch)
            else:
                direction, _ = semi_stochastic_gradient(
                    rows, side.run.algo, current, snapshot, batch, mu.to(current).unsqueeze(0),
                    weights,
                )  # fmt: skip
            current = current + self.adam.direction(direction[0].cpu()).to(current)
        return current[0].detach().cpu().clone()

    def round_stats(self) -> dict[str, Any]:
        return dict(self.stats)

    def sampled_trajectories(self) -> int:
        return int(self.stats.get("trajectories", 0))

    def state(self) -> SavedState:
        return self.adam.state()

    def restore(self, state: SavedState) -> None:
        self.adam.restore(state)
