"""The round loop of Algorithms 1 and 2, independent of how agents are reached.

Each round: the strategy selects agents, the pool collects their local updates (every pool
checks them the same way), the strategy aggregates the accepted ones into θ̃, the round is
recorded; every E rounds the unified policy is evaluated. Nothing else lives here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.ids import agent_id_of
from fedhpg.common.records.types import EvaluationStats, RoundResult, SavedState
from fedhpg.common.runtime import timeline
from fedhpg.server.bound_report import round_bound
from fedhpg.server.participation import make_participation
from fedhpg.server.pools import AgentPool, FederationError, RoundAnswers, SkippedRound
from fedhpg.server.privacy import PrivateRounds
from fedhpg.server.replan import make_replanner
from fedhpg.server.secure_sum import sum_problem
from fedhpg.server.strategies import Strategy
from fedhpg.server.tolerance import tolerance_shortfall
from fedhpg.server.validation import diverged, reasons

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class RoundRecord:
    """What ``metrics.jsonl`` holds for one round (schema: docs/metrics.md)."""

    round: int
    wall_time_s: float
    round_time_s: float
    result: RoundResult
    """The aggregated updates (rows in agent-index order; none where the round was skipped)."""
    name: Callable[[int], str] = agent_id_of
    """Each agent's id."""
    trajectories_per_agent: float = 0.0
    """Cumulative trajectories sampled so far, the agents' and the strategy's own (fedpgbr's
    server), divided by K (the x-axis of published curves)."""
    eval: dict[str, EvaluationStats] | None = None
    eval_time_s: float | None = None
    """Wall time of this round's evaluation, where there was one (in ``wall_time_s``, not in
    ``round_time_s``)."""
    failures: dict[str, str] = field(default_factory=dict)
    stragglers: list[str] = field(default_factory=list)
    selected: list[int] = field(default_factory=list)
    """The agent indices asked to train (participation, then the strategy's select)."""
    bound: dict[str, Any] | None = None
    """Theorem 1's terms from the agents' estimates (``algo.bound_estimates``)."""
    plan: dict[str, Any] | None = None
    """The budgets re-planned after this round (``agents.plan``), in force from the next."""
    emulated_clock_s: float | None = None
    """Buffered rounds: the emulated time at which this θ̃ was aggregated."""
    staleness: list[int] | None = None
    """Buffered rounds: each aggregated update's staleness, in the order of ``agents``."""
    stale: dict[str, int] = field(default_factory=dict)
    """Buffered rounds: agent id → staleness of the updates dropped past the bound."""
    strategy: dict[str, Any] = field(default_factory=dict)
    """What the strategy reports of its aggregation (:meth:`Strategy.round_stats`)."""
    privacy: dict[str, Any] | None = None
    """``privacy.mode`` ≠ none: ε and δ so far, σ, the clip, the inputs aggregated."""
    secure: dict[str, Any] | None = None
    """A secure round that was skipped: ``{"failed": why}`` (θ̃ is the round before's)."""
    aggregated: int | None = None
    """Where the sample is secret (``privacy=dp`` sampled: ``agents``, ``selected``,
    ``failures`` and ``stragglers`` left empty), the number of updates aggregated."""

    @property
    def update_count(self) -> int:
        """How many updates the round aggregated."""
        return len(self.result) if self.aggregated is None else self.aggregated

    @functools.cached_property
    def agent_rows(self) -> list[dict[str, Any]]:
        """``agents[]`` of metrics.jsonl, built once for every writer of the record (metrics,
        TensorBoard): read them, never change them."""
        rows = []
        for index, stats in zip(self.result.agents, self.result.stats.records(), strict=True):
            row = stats.to_json()
            row["id"], row["index"] = self.name(index), index
            rows.append(row)
        return rows

    def to_json(self) -> dict[str, Any]:
        record: dict[str, Any] = {
            "round": self.round,
            "wall_time_s": self.wall_time_s,
            "round_time_s": self.round_time_s,
            "trajectories_per_agent": self.trajectories_per_agent,
            **({"selected": list(self.selected)} if self.aggregated is None else {}),
            "agents": self.agent_rows,
        }
        if self.eval is not None:
            record["eval"] = {agent: stats.to_json() for agent, stats in self.eval.items()}
        if self.eval_time_s is not None:
            record["eval_time_s"] = self.eval_time_s
        record["updates"] = self.update_count
        if self.failures:
            record["failures"] = dict(self.failures)
        if self.stragglers:
            record["stragglers"] = list(self.stragglers)
        if self.bound is not None:
            record["bound"] = dict(self.bound)
        if self.plan is not None:
            record["plan"] = dict(self.plan)
        if self.emulated_clock_s is not None:
            record["emulated_clock_s"] = self.emulated_clock_s
        if self.staleness is not None:
            record["staleness"] = list(self.staleness)
        if self.stale:
            record["stale"] = dict(self.stale)
        if self.strategy:
            record["strategy"] = dict(self.strategy)
        if self.privacy is not None:
            rest = dict(self.privacy)
            if "epsilon" in rest:
                record["epsilon"], record["delta"] = rest.pop("epsilon"), rest.pop("delta")
            if "epsilon_server" in rest:
                record["epsilon_server"] = rest.pop("epsilon_server")
            record["privacy"] = rest
        if self.secure is not None:
            record["secure"] = dict(self.secure)
        return record


RoundCallback = Callable[[RoundRecord, torch.Tensor], None]


def diverged_message(run: RunConfig, round_number: int) -> str:
    """One line for a run whose every local update diverged: what was set, and what to change.

    Every update being non-finite means the local steps themselves blew up (not one bad
    agent), so the remedy is in the step sizes, not in the agents."""
    algo, strategy = run.algo, run.strategy
    clip = "off" if algo.grad_clip is None else f"{algo.grad_clip:g}"
    server = strategy.name
    if "step_size" in strategy.params:
        server += f" (strategy.params.step_size={strategy.params['step_size']:g})"
    return (
        f"round {round_number}: every agent's update was rejected: parameters contain NaN or "
        f"Inf; the local steps diverged with algo.step_size={algo.step_size:g} "
        f"(algo.optimizer={algo.optimizer}, algo.grad_clip={clip}, strategy={server}, "
        f"env.family={run.env.family}): lower algo.step_size below {algo.step_size:g}, set "
        f"algo.grad_clip, or run the family's preset, env={run.env.family}, without "
        f"overriding these (plain steps of size 1 with strategy=fedadam)"
    )


def should_evaluate(run: RunConfig, round_number: int) -> bool:
    return round_number % run.eval.every == 0 or round_number == run.rounds


def mean_return(evaluation: dict[str, EvaluationStats]) -> float:
    """An evaluation's mean return over the agents (``eval.stop_at``, the best checkpoint)."""
    return sum(stats.return_mean for stats in evaluation.values()) / len(evaluation)


def reached_target(
    run: RunConfig, round_number: int, evaluation: dict[str, EvaluationStats] | None
) -> bool:
    """Whether this round's evaluation reached ``eval.stop_at`` (logged when it did)."""
    target = run.eval.stop_at
    if target is None or not evaluation:
        return False
    value = mean_return(evaluation)
    if value < target:
        return False
    logger.info(
        "round %d: mean evaluation return %.4g reached eval.stop_at=%g: the run stops",
        round_number,
        value,
        target,
    )
    return True


@dataclass
class RunProgress:
    """Where a run stands between rounds: what a checkpoint must hold to continue it."""

    next_round: int = 1
    trajectories_per_agent: float = 0.0
    elapsed_s: float = 0.0
    """Wall time of the rounds already done (before a restart, if any)."""
    strategy_state: SavedState = field(default_factory=SavedState)
    plan_state: dict[str, Any] = field(default_factory=dict)
    """``agents.plan``: the plan in force and the window it is re-made from."""
    schedule_state: SavedState | None = None
    """Buffered rounds: the in-flight updates and the emulated clock (server/buffered.py)."""
    privacy_state: dict[str, Any] = field(default_factory=dict)
    """``privacy.mode`` ≠ none: the rounds accounted, σ and the clip (server/privacy.py)."""


class Coordinator:
    """Drives ``run.rounds`` rounds; rounds are numbered from 1 as in the paper."""

    def __init__(
        self,
        *,
        run: RunConfig,
        pool: AgentPool,
        strategy: Strategy[Any],
        theta: torch.Tensor,
        progress: RunProgress | None = None,
        on_round: list[RoundCallback] | None = None,
        privacy: PrivateRounds | None = None,
    ) -> None:
        self.run = run
        self.privacy = privacy
        self.pool = pool
        self.strategy = strategy
        self.theta = theta
        self.progress = progress or RunProgress()
        self.on_round = on_round or []
        self._unwritten: tuple[RoundRecord, torch.Tensor] | None = None
        """The last round's record and θ̃, until written (:meth:`_write_record`)."""
        self.participation = make_participation(run)
        self.failed_in_a_row = 0
        """Secure rounds skipped since the last one aggregated (``server.max_failed_rounds``)."""
        self.stopped_early: int | None = None
        """The round whose evaluation reached ``eval.stop_at``, where one did."""
        self.replanner = make_replanner(run, self.progress.plan_state)
        shortfall = tolerance_shortfall(run, strategy)  # refused at validation unless 'warn'
        if shortfall is not None:
            logger.warning("%s", shortfall)
        if self.progress.next_round > 1:
            strategy.restore(self.progress.strategy_state)
            if privacy is not None:
                privacy.restore(self.progress.privacy_state, run)

    def _aggregate_or_skip(
        self, round_number: int, answers: RoundAnswers, selected: int
    ) -> str | None:
        """:meth:`_aggregate`; a secure round that cannot be aggregated is skipped (θ̃ stays,
        logged): why, or None. Past ``server.max_failed_rounds`` skipped in a row the run
        stops (FederationError), its checkpoint of the last round aggregated intact."""
        try:
            self._aggregate(round_number, answers, selected)
        except SkippedRound as skipped:
            self.failed_in_a_row += 1
            limit = self.run.server.max_failed_rounds
            if self.failed_in_a_row > limit:
                raise FederationError(
                    f"{skipped}; {self.failed_in_a_row} secure rounds in a row could not be "
                    f"aggregated (server.max_failed_rounds={limit}): the run stops, θ̃ of round "
                    f"{round_number - self.failed_in_a_row} kept in the checkpoints"
                ) from None
            logger.warning("%s: round skipped, θ̃ of round %d kept", skipped, round_number - 1)
            return skipped.reason
        self.failed_in_a_row = 0
        return None

    def _aggregate(self, round_number: int, answers: RoundAnswers, selected: int) -> None:
        result, failures = answers.result, answers.failures
        failed = answers.secure is not None and answers.secure.failed is not None
        if not len(result) and not failed:  # a failed secure round: the privacy step says why
            if diverged(failures):
                raise FederationError(diverged_message(self.run, round_number))
            raise FederationError(
                f"round {round_number}: no update to aggregate (rejected: {reasons(failures)})"
            )
        if self.privacy is not None:
            average = self.privacy.aggregate(round_number, self.theta, answers, selected)
            if answers.secure is not None:  # only the sum was seen: check what is public of it
                step = (average - self.theta).numpy()
                problem = sum_problem(
                    self.run, answers.secure, step, weighted=self.privacy.weighted
                )
                if problem is not None:
                    raise SkippedRound(round_number, problem)
            theta = self.strategy.from_average(round_number, self.theta, average).detach()
        else:
            theta = self.strategy.aggregate(
                round_number, self.theta, result, reasons(failures)
            ).detach()
        fits = theta.shape == self.theta.shape and theta.dtype == self.theta.dtype
        # numpy's isfinite: torch's allocates a bool tensor and costs ~14x as much per round
        if not fits or not bool(np.isfinite(theta.numpy()).all()):
            raise FederationError(
                f"round {round_number}: strategy {self.strategy.name!r} produced a θ̃ "
                f"({theta.dtype}, shape {tuple(theta.shape)}) that is not finite or not the "
                f"run's; θ̃ of round {round_number - 1} is kept in the checkpoints"
            )
        self.theta = theta

    def run_rounds(self) -> torch.Tensor:
        """The rounds from the progress's next on. A round's record (metrics.jsonl, TensorBoard,
        its checkpoint) is written while the next round's agents train,
        not between the rounds, where the agents would wait for it; always before anything
        else of the next round is recorded, and before this returns or raises."""
        started = time.perf_counter() - self.progress.elapsed_s
        hiding = (
            self.privacy.hiding_names(self.pool.agent_ids)
            if self.privacy is not None
            else contextlib.nullcontext()
        )
        try:
            with hiding:
                for round_number in range(self.progress.next_round, self.run.rounds + 1):
                    self._round(round_number, started)
                    if self.stopped_early is not None:
                        break
        finally:
            self._write_record()
        return self.theta

    def _round(self, round_number: int, started: float) -> None:
        """Select, train (the round before's record is written meanwhile), aggregate, evaluate;
        this round's record is left for the next round's training (:attr:`_unwritten`)."""
        round_started = time.perf_counter()
        timeline.mark("server", "round-start", round_number)
        # participation first: every strategy chooses among the agents that take part
        participating = self.participation.select(round_number)
        selected = self.strategy.select(round_number, participating)
        budgets = self.replanner.budgets() if self.replanner is not None else None
        private = None
        if self.privacy is not None:
            self.privacy.check_budget(round_number, selected)
            if self.privacy.secure:
                # the noise shares are sized from the agents that run the protocol
                taking_part = self.pool.secure_participants(selected)
                private = self.privacy.round_privacy(len(taking_part))
        answers = self.pool.train(
            round_number,
            self.theta,
            selected,
            budgets=budgets,
            while_training=self._write_record,
            private=private,
        )
        self._write_record()  # where the pool did not call it
        timeline.mark("server", "answers-in", round_number)
        skipped = self._aggregate_or_skip(round_number, answers, len(selected))
        round_time = time.perf_counter() - round_started
        timeline.mark("server", "aggregated", round_number)
        evaluation, eval_time = None, None
        if should_evaluate(self.run, round_number):
            evaluated = time.perf_counter()
            evaluation = self.pool.evaluate(round_number, self.theta, self.run.eval.episodes)
            eval_time = time.perf_counter() - evaluated
            if reached_target(self.run, round_number, evaluation):
                self.stopped_early = round_number
        wall_time = time.perf_counter() - started
        progress = self.progress
        progress.next_round = round_number + 1
        sampled = sum(answers.result.stats.trajectories)
        sampled += self.strategy.sampled_trajectories()  # the server's own (fedpgbr's)
        progress.trajectories_per_agent += sampled / self.run.agents.num_agents
        progress.elapsed_s = wall_time
        progress.strategy_state = self.strategy.state()
        if self.privacy is not None:
            progress.privacy_state = self.privacy.state()
        plan = None
        if self.replanner is not None:
            plan = self.replanner.observe(round_number, answers.result)
            progress.plan_state = self.replanner.saved()
        record = RoundRecord(
            round=round_number,
            wall_time_s=wall_time,
            round_time_s=round_time,
            result=answers.result if skipped is None else _nothing(answers.result),
            name=answers.name,
            trajectories_per_agent=progress.trajectories_per_agent,
            eval=evaluation,
            eval_time_s=eval_time,
            failures=reasons(answers.failures),
            stragglers=answers.stragglers,
            selected=sorted(selected),
            bound=round_bound(self.run, answers.result, budgets)
            if self.run.algo.bound_estimates
            else None,
            plan=plan,
            strategy={} if skipped else self.strategy.round_stats(),
            privacy=self.privacy.round_stats() if self.privacy is not None else None,
            secure=None if skipped is None else {"failed": skipped},
        )
        if self.privacy is not None and self.privacy.hides_sample:
            # the accounted ε is amplified by a sample nobody else may learn: no record of it
            record = dataclasses.replace(
                record,
                result=_nothing(answers.result),
                failures={},
                stragglers=[],
                selected=[],
                bound=None,
                aggregated=len(answers.result),
            )
        self._unwritten = (record, self.theta)

    def _write_record(self) -> None:
        """The last round's record to every ``on_round`` callback, once (none is retried)."""
        if self._unwritten is None:
            return
        (record, theta), self._unwritten = self._unwritten, None
        timeline.mark("server", "recording", record.round)
        for callback in self.on_round:
            callback(record, theta)
        timeline.mark("server", "recorded", record.round)


def _nothing(result: RoundResult) -> RoundResult:
    """A record's result of no update (a skipped round's; one whose sample is secret)."""
    return RoundResult.empty(result.round, result.thetas.shape[1])
