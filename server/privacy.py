"""The server's side of ``privacy=``: clipping, noise, the accountant and the budget.

One :class:`PrivateRounds` per run (built by :func:`fedhpg.server.assembly.check_run`) turns a
round's answers into θ̃ in place of the strategy's own ``aggregate``:

- ``dp``: the server clips each Δ_k = θ_k − θ̃ to C, sums the contributions
  (:mod:`fedhpg.common.privacy.contribution`) and adds N(0, σ²C²) to the sum (central noise);
- ``secagg``: the pool hands over the unmasked sum of the agents' contributions (it never saw
  one alone): the exact average of the included agents' updates;
- ``dp_secagg``: the same sum, to which every agent added its share of the noise.

With DP the average divides by the expected number of participants (public), each round is
accounted (:mod:`fedhpg.common.privacy.accounting`), and a round that would take ε past the
budget is refused before it starts: the run stops in one line, its last checkpoint intact.
The strategy then makes θ̃ from the average (``from_average``: the average itself, or
fedadam's step towards it). Checkpoints keep the rounds accounted, σ and the clip.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import torch

from fedhpg.common.config import ConfigError, RunConfig
from fedhpg.common.privacy import accounting, dp
from fedhpg.common.privacy.accounting import Sampling
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy, average, contribution
from fedhpg.common.types import AgentUpdate
from fedhpg.server.pools import FederationError, RoundAnswers

logger = logging.getLogger(__name__)


class BudgetExhausted(FederationError):
    """The next round would take ε past ``privacy.epsilon``."""


def sampling_of(run: RunConfig) -> Sampling:
    """How the run draws a round's agents, as the accountant sees it (a trace is public and
    not random: every round counts in full, as with ``all``)."""
    participation = run.strategy.participation
    population = run.agents.num_agents
    if participation.mode == "uniform" and participation.per_round is not None:
        return Sampling(kind="fixed", population=population, sample=participation.per_round)
    return Sampling(kind="all", population=population)


class PrivateRounds:
    """Clip, noise, account and average the rounds of a run with ``privacy.mode`` ≠ none."""

    def __init__(self, run: RunConfig, *, weighted: bool) -> None:
        settings = run.privacy
        self.mode = settings.mode
        self.settings = settings
        self.weighted = weighted
        self.sampling = sampling_of(run)
        population = run.agents.num_agents
        self.delta = settings.delta if settings.delta is not None else 1.0 / population**1.1
        self.target = settings.epsilon
        self.clip = settings.clip
        self.accounted = 0
        self.noise_multiplier = 0.0
        self.count_std: float | None = None
        self.update_multiplier = 0.0
        self._seed = settings.noise_seed
        self._last: dict[str, Any] = {}
        if self.dp:
            if settings.noise_multiplier is not None:
                self.noise_multiplier = settings.noise_multiplier
            else:
                assert self.target is not None  # validated
                self.noise_multiplier = accounting.calibrate(
                    self.target, self.sampling, run.rounds, self.delta
                )
            self._set_count_noise(run)

    def _set_count_noise(self, run: RunConfig) -> None:
        if self.settings.adaptive_clip:
            # Andrew et al.'s m/20, but never below σ: a small round's count would otherwise
            # spend most of the budget (the update's own multiplier is then 2/√3 σ at most)
            self.count_std = self.settings.count_std or max(
                self.sampling.expected / 20, self.noise_multiplier
            )
        try:
            self.update_multiplier = dp.update_noise_multiplier(
                self.noise_multiplier, self.count_std
            )
        except ValueError as error:
            raise ConfigError("privacy.count_std", str(error)) from None

    @property
    def dp(self) -> bool:
        return self.mode in ("dp", "dp_secagg")

    @property
    def secure(self) -> bool:
        """Whether the pools aggregate securely (the server never sees a θ_k)."""
        return self.mode in ("secagg", "dp_secagg")

    def epsilon(self, rounds: int | None = None) -> float:
        """ε after ``rounds`` accounted rounds (default: so far)."""
        spent = self.accounted if rounds is None else rounds
        return accounting.epsilon(self.noise_multiplier, self.sampling, spent, self.delta)

    def check_budget(self, round_number: int) -> None:
        """Refuse ``round_number`` if it would take ε past the budget."""
        if not self.dp or self.target is None:
            return
        after = self.epsilon(self.accounted + 1)
        if after > self.target:
            raise BudgetExhausted(
                f"privacy.epsilon: round {round_number} would spend ε = {after:.4g} > the "
                f"budget {self.target:g} (δ = {self.delta:.3g}, σ = {self.noise_multiplier:.4g},"
                f" {self.accounted} rounds accounted): the run stops here, its checkpoint of "
                f"round {round_number - 1} kept"
            )

    def min_inputs(self, participants: int) -> int:
        """The fewest contributions a round's sum may hold: with distributed noise, enough
        shares of it to reach σC (the secure aggregation threshold of the round)."""
        if self.mode != "dp_secagg":
            return 1
        return min(math.floor(self.settings.secagg.threshold * participants) + 1, participants)

    def round_privacy(self, participants: int) -> RoundPrivacy:
        """What the round's agents (or the server, for central noise) contribute with."""
        clip = self.clip if self.dp else 0.0
        noise_std = count_std = 0.0
        if self.mode == "dp_secagg":
            shares = self.min_inputs(participants)
            noise_std = dp.per_agent_std(self.update_multiplier * clip, shares)
            count_std = dp.per_agent_std(self.count_std or 0.0, shares)
        return RoundPrivacy(
            clip=clip,
            noise_std=noise_std,
            count_std=count_std,
            bound=self.settings.secagg.range if self.secure else math.inf,
            weighted=self.weighted,
        )

    def aggregate(
        self,
        round_number: int,
        theta: torch.Tensor,
        answers: RoundAnswers,
        selected: int,
    ) -> torch.Tensor:
        """θ̄ = θ̃ + the round's private average update (the strategy takes it from there)."""
        if self.secure:
            if answers.secure is None:
                raise FederationError(f"round {round_number}: no secure sum came back")
            total, inputs = answers.secure.total, answers.secure.inputs
            fewest = self.min_inputs(selected)
            if inputs < fewest:
                raise FederationError(
                    f"round {round_number}: {inputs} of {selected} agents' inputs were "
                    f"aggregated, fewer than the {fewest} whose noise shares reach σC "
                    "(privacy.secagg.threshold): the round is not released"
                )
        else:
            total, inputs = self._central_sum(round_number, theta, answers.updates, selected)
        denominator = self.sampling.expected if self.dp else None
        step, unclipped = average(total, denominator)
        clip_used = self.clip
        if self.dp:
            self.accounted += 1
            if self.settings.adaptive_clip:
                self.clip = dp.next_clip(
                    self.clip, unclipped, self.settings.target_quantile, self.settings.clip_rate
                )
        self._last = {"inputs": inputs, **({"clip": clip_used} if self.dp else {})}
        return theta + torch.from_numpy(step).to(theta.dtype)

    def _central_sum(
        self, round_number: int, theta: torch.Tensor, updates: list[AgentUpdate], selected: int
    ) -> tuple[np.ndarray, int]:
        settings = self.round_privacy(selected)
        total = np.zeros(theta.numel() + EXTRA)
        for update in updates:
            total += contribution(update.theta - theta, update.stats.trajectories, settings)
        noise = dp.noise_stream(self._seed, round_number, None)
        total[:-EXTRA] += dp.gaussian(noise, theta.numel(), self.update_multiplier * self.clip)
        if self.count_std is not None:
            total[-1] += dp.gaussian(noise, 1, self.count_std)[0]
        return total, len(updates)

    def round_stats(self) -> dict[str, Any]:
        """metrics.jsonl's ``epsilon``, ``delta`` and ``privacy`` of the last round."""
        stats: dict[str, Any] = {"mode": self.mode, **self._last}
        if self.dp:
            stats.update(
                epsilon=self.epsilon(),
                delta=self.delta,
                noise_multiplier=self.noise_multiplier,
                rounds_accounted=self.accounted,
            )
        return stats

    def summary(self) -> dict[str, Any]:
        """summary.json's ``privacy``."""
        stats = {"mode": self.mode, "secure_aggregation": self.secure}
        if self.dp:
            stats.update(
                epsilon=self.epsilon(),
                delta=self.delta,
                epsilon_budget=self.target,
                noise_multiplier=self.noise_multiplier,
                rounds_accounted=self.accounted,
                clip=self.clip,
                neighbouring=self.sampling.relation,
            )
        return stats

    def state(self) -> dict[str, Any]:
        return {"accounted": self.accounted, "sigma": self.noise_multiplier, "clip": self.clip}

    def restore(self, state: dict[str, Any], run: RunConfig) -> None:
        """Continue the accounting of a resumed run: its σ (never re-calibrated for a longer
        run), rounds accounted and clip."""
        if not state:
            return
        self.accounted = int(state["accounted"])
        self.clip = float(state["clip"])
        if self.dp:
            self.noise_multiplier = float(state["sigma"])
            self._set_count_noise(run)
