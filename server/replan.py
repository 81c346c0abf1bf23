"""``agents.plan=theorem1``: the server re-plans every agent's B_k, τ_k while the run goes.

The first ``plan_every`` rounds run the configured budgets: before any round nothing is
observed, and Theorem 1's constants come from the agents' own estimates
(``algo.bound_estimates``), so the first plan is made after round P from what those rounds
showed. Then after every P rounds (P, 2P, ...) the plan is re-made from the last P rounds alone:

- each agent's emulated seconds per trajectory (its updates' ``emulated_s`` less its two
  messages, over its trajectories): a device that slows down is priced at its new speed;
- σ_k² the mean of agent k's σ̂_k², M the largest M̂_k, L the largest secant L̂_k (below);
- the gap J(θ*) − J(θ̃_0): ``agents.plan_max_return`` (default the horizon) less round 1's
  mean training return;
- the round time: ``agents.plan_round_s`` emulated seconds (a round lasts as long as its
  slowest agent), by default the slowest round of the first P rounds: the configured
  budgets' pace.

:func:`fedhpg.common.learning.planning.plan_for_rounds` then minimises eq. 7 for the rounds left
(T is the run's: it still ends after ``rounds`` rounds), every agent's round within the round
time: a device that slows down gets less work, one that speeds up more. The round time, not
a total, is what is held: a plan is priced at the last P rounds' speeds, so when the speeds
drift a round may run over it, and a total would be overspent without remedy.

An agent not seen in the window (partial participation) keeps the
speed and variance last seen, or, never seen, the window's slowest speed and mean variance.
L and M are the window's when it measured them, else the last plan's (a plan of τ_k = 1
measures no secant). No L̂ > 0 yet, or a round time too short for the smallest budgets: the
plan in force is kept (logged).

Everything the next plan needs is in :meth:`Replanner.state` (plain numbers): checkpoints
keep it, so a resumed run re-plans exactly as the uninterrupted one.
"""

from __future__ import annotations

import logging
import statistics
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.device import device_for, message_bytes
from fedhpg.common.heterogeneity.variants import training_horizon, variant_of
from fedhpg.common.learning.planning import Constants, Limits, plan_for_rounds
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.records.types import RoundResult

logger = logging.getLogger(__name__)


@dataclass
class PlanState:
    """The plan in force and what the rounds since it was made observed (msgpack-able)."""

    batch_sizes: list[int] = field(default_factory=list)
    """B_k in force (empty: the configured budgets)."""
    local_iters: list[int] = field(default_factory=list)
    round_s: float = 0.0
    """The round time planned for (``plan_round_s``, or the default once resolved)."""
    window_s: float = 0.0
    """The slowest round of the window (to resolve the default round time)."""
    initial_return: float | None = None
    seconds: list[float] = field(default_factory=list)
    """Per agent: emulated seconds of trajectories in the window, less messages."""
    trajectories: list[int] = field(default_factory=list)
    variance_sums: list[float] = field(default_factory=list)
    variance_counts: list[int] = field(default_factory=list)
    second_moment: float = 0.0
    smoothness: float = 0.0
    last_speed: list[float] = field(default_factory=list)
    """Per agent: seconds per trajectory at the last plan (0: never seen)."""
    last_variance: list[float] = field(default_factory=list)
    last_smoothness: float = 0.0
    """L at the last plan: a plan of τ_k = 1 measures no secant, and L is J's, not a
    device's, so it is kept until a window measures one."""
    last_second_moment: float = 0.0


class Replanner:
    """Decides each round's budgets for ``agents.plan=theorem1``."""

    def __init__(self, run: RunConfig, state: Mapping[str, Any] | None = None) -> None:
        self.run = run
        self.num_agents = run.agents.num_agents
        self.overhead = round_overhead_s(run)
        self.limits = Limits(
            batch_max=run.agents.plan_batch_max, local_iters_max=run.agents.plan_local_iters_max
        )
        self.state = PlanState(**dict(state)) if state else PlanState()
        if not self.state.seconds:
            self._clear_window()
            self.state.last_speed = [0.0] * self.num_agents
            self.state.last_variance = [0.0] * self.num_agents
            self.state.round_s = run.agents.plan_round_s

    def _clear_window(self) -> None:
        k = self.num_agents
        s = self.state
        s.seconds, s.trajectories = [0.0] * k, [0] * k
        s.variance_sums, s.variance_counts = [0.0] * k, [0] * k
        s.second_moment = s.smoothness = 0.0

    def budgets(self) -> dict[int, dict[str, int]]:
        """The round's budget fields per agent (empty: the configured budgets)."""
        return {
            k: {"batch_size": b, "local_iters": t}
            for k, (b, t) in enumerate(
                zip(self.state.batch_sizes, self.state.local_iters, strict=True)
            )
        }

    def saved(self) -> dict[str, Any]:
        return asdict(self.state)

    def observe(self, round_number: int, result: RoundResult) -> dict[str, Any] | None:
        """Take in round ``round_number``'s accepted updates; after every ``plan_every`` rounds
        re-plan and return the round record's ``plan`` entry (None when no plan is made)."""
        s = self.state
        stats = result.stats
        if s.initial_return is None and len(result):
            s.initial_return = statistics.fmean(stats.train_return)
        s.window_s = max(s.window_s, max(stats.emulated_s, default=0.0))
        for k, update in zip(result.agents, stats.records(), strict=True):
            s.seconds[k] += max(update.emulated_s - self.overhead[k], 0.0)
            s.trajectories[k] += update.trajectories
            algorithm = update.algorithm
            if "bound_variance" in algorithm:
                s.variance_sums[k] += float(algorithm["bound_variance"])
                s.variance_counts[k] += 1
                s.second_moment = max(s.second_moment, float(algorithm["bound_second_moment"]))
            s.smoothness = max(s.smoothness, float(algorithm.get("bound_smoothness", 0.0)))
        every = self.run.agents.plan_every
        if round_number % every != 0 or round_number >= self.run.rounds:
            return None
        if s.round_s <= 0.0:  # the default: the configured budgets' pace
            s.round_s = s.window_s
        record = self._replan(round_number)
        self._clear_window()
        s.window_s = 0.0
        return record

    def _window_estimates(self) -> tuple[list[float], list[float]]:
        s = self.state
        for k in range(self.num_agents):
            if s.trajectories[k] > 0 and s.seconds[k] > 0:
                s.last_speed[k] = s.seconds[k] / s.trajectories[k]
            if s.variance_counts[k] > 0:
                s.last_variance[k] = s.variance_sums[k] / s.variance_counts[k]
        seen_speeds = [c for c in s.last_speed if c > 0]
        seen_variances = [v for v, c in zip(s.last_variance, s.last_speed, strict=True) if c > 0]
        slowest = max(seen_speeds, default=0.0)
        mean_variance = statistics.fmean(seen_variances) if seen_variances else 0.0
        speeds = [c if c > 0 else slowest for c in s.last_speed]
        variances = [
            v if c > 0 else mean_variance
            for v, c in zip(s.last_variance, s.last_speed, strict=True)
        ]
        return speeds, variances

    def _replan(self, round_number: int) -> dict[str, Any] | None:
        s = self.state
        speeds, variances = self._window_estimates()
        if s.smoothness > 0.0:
            s.last_smoothness = s.smoothness
        if s.second_moment > 0.0:
            s.last_second_moment = s.second_moment
        if s.last_smoothness <= 0.0 or not all(c > 0 for c in speeds):
            logger.warning(
                "round %d: no plan made (no agent estimated L > 0, or none was timed); the "
                "budgets in force are kept",
                round_number,
            )
            return None
        max_return = self.run.agents.plan_max_return
        if max_return is None:
            max_return = float(training_horizon(self.run, variant_of(self.run, 0)))
        constants = Constants(
            gap=max(max_return - (s.initial_return or 0.0), 0.0),
            step_size=self.run.algo.step_size,
            smoothness=s.last_smoothness,
            second_moment=s.last_second_moment,
            variances=tuple(variances),
        )
        try:
            plan = plan_for_rounds(
                constants=constants,
                seconds_per_trajectory=speeds,
                overhead_s=self.overhead,
                total_s=s.round_s * (self.run.rounds - round_number),
                rounds=self.run.rounds - round_number,
                limits=self.limits,
            )
        except ValueError as error:
            logger.warning(
                "round %d: no plan made (%s); the budgets in force are kept", round_number, error
            )
            return None
        s.batch_sizes, s.local_iters = list(plan.batch_sizes), list(plan.local_iters)
        logger.info(
            "round %d: re-planned budgets B=%s tau=%s (bound %.4g over the %d rounds left, "
            "the slowest %.4g s of the %.4g s a round may take)",
            round_number,
            s.batch_sizes,
            s.local_iters,
            plan.bound,
            plan.rounds,
            plan.round_s,
            s.round_s,
        )
        return {
            "round": round_number,
            "batch_size": list(s.batch_sizes),
            "local_iters": list(s.local_iters),
            "bound": plan.bound,
            "rounds": plan.rounds,
            "round_s": plan.round_s,
            "round_limit_s": s.round_s,
            "seconds_per_trajectory": list(speeds),
            "step_size_ok": plan.step_size_ok,
        }


def round_overhead_s(run: RunConfig, round_index: int = 1) -> list[float]:
    """Each agent's fixed cost per round: θ̃ down and θ up (the counted clock charges both;
    the measured clock charges the latency only in agent processes, the in-process pool none)."""
    del round_index  # messages do not depend on the speed schedule
    size = message_bytes(initial_theta(variant_of(run, 0), run).numel())
    devices = [device_for(run, k) for k in range(run.agents.num_agents)]
    return [2 * d.transfer_s(size) if d.counted else 0.0 for d in devices]


def make_replanner(run: RunConfig, state: Mapping[str, Any] | None) -> Replanner | None:
    return Replanner(run, state) if run.agents.plan == "theorem1" else None
