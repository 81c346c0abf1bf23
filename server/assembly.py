"""One way to assemble a run: config → strategy, algorithm, θ̃, sinks, pool, coordinator.

Every way of starting a federation comes through here, so a run is checked in one order and
built of the same parts whatever starts it:

- :func:`check_run` is every server-side check of a validated config, before anything is
  started or written (ConfigError naming the key): the strategy, built once, against the
  algorithm's updates (:func:`~fedhpg.server.strategies.check_takes`), participation, a
  robust rule's tolerance, and what the round policy can take. ``fedhpg-run`` and
  ``fedhpg-cluster`` call it before they fork or submit anything.
- :func:`assemble` builds a checked run's parts: θ̃ and the progress (θ̃_0, or the newest
  valid checkpoint's on resume), and with a run directory its ``config.json`` and sinks
  (``metrics.jsonl``, checkpoints, TensorBoard) ahead of the caller's callbacks.
  :meth:`Assembly.run_rounds` drives them over an agent pool with the coordinator the round
  policy calls for, :meth:`Assembly.finish` writes ``summary.json``.
- :func:`run_in_process` is the in-process runner on top of them (tests, sweeps, the API).

``fedhpg-server`` (:mod:`fedhpg.server.serving`), the Python API and the in-process runner
assemble their runs here; run-time code never imports an entry point (import-linter checks).
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from fedhpg.common.configuration.config import RunConfig, attacking_agents, to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.placement import agents_per_host
from fedhpg.common.configuration.run_keys import fixed_difference
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.common.heterogeneity.variants import discount, run_variants, variant_of
from fedhpg.common.learning.components import validate_run
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.privacy.graph import GraphError, round_plan
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.runtime.run_files import PROGRESS_NAME
from fedhpg.envs.base import EnvVariant
from fedhpg.server.buffered import BufferedCoordinator
from fedhpg.server.checkpoint import (
    BEST_RETURN,
    Checkpoint,
    CheckpointError,
    best_checkpoint,
    latest_valid_checkpoint,
    save_best,
    save_checkpoint,
    write_atomic,
)
from fedhpg.server.coordinator import (
    Coordinator,
    RoundCallback,
    RoundRecord,
    RunProgress,
    mean_return,
)
from fedhpg.server.metrics import MetricsWriter, record_marks, tensorboard_sink
from fedhpg.server.pools import AgentPool
from fedhpg.server.pools.inprocess import make_in_process_pool
from fedhpg.server.privacy import PrivateRounds
from fedhpg.server.run_dir import RunDirectory, RunDirectoryError
from fedhpg.server.sinks import ProgressCsv, wandb_sink
from fedhpg.server.strategies import Strategy, validate_strategy

logger = logging.getLogger(__name__)


# --- checks -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class CheckedRun:
    """A run whose config passed :func:`check_run`, with the strategy built for it."""

    run: RunConfig
    strategy: Strategy[Any]
    privacy: PrivateRounds | None = None
    """``privacy.mode`` ≠ none: clipping, noise, accounting (σ already calibrated)."""

    @functools.cached_property
    def first(self) -> EnvVariant:
        """Agent 0's variant: the run's spaces and θ̃_0's policy."""
        return variant_of(self.run, 0)

    @functools.cached_property
    def initial_theta(self) -> torch.Tensor:
        """θ̃_0."""
        return initial_theta(self.first, self.run)


def check_run(run: RunConfig, *, distributed: bool) -> CheckedRun:
    """Every server-side check of ``run`` (a config validated at its entry point), in one
    order, and its strategy, built once; ``distributed``: agents in processes of their own."""
    strategy = validate_strategy(run)
    _check_round_policy(run, strategy, distributed=distributed)
    return CheckedRun(run, strategy, _check_privacy(run, strategy))


def _check_privacy(run: RunConfig, strategy: Strategy[Any]) -> PrivateRounds | None:
    """What ``privacy.mode`` cannot combine with (config.py checks its keys' own ranges), and
    the run's private rounds, σ calibrated to its budget."""
    mode = run.privacy.mode
    if mode == "none":
        return None
    try:
        import cryptography  # noqa: F401
        import dp_accounting  # noqa: F401
    except ImportError:
        raise ConfigError(
            "privacy.mode",
            f"privacy.mode={mode} needs the optional packages: pip install 'fedhpg[privacy]'",
        ) from None
    averaging = strategy.averaging()
    if averaging is None:
        raise ConfigError(
            "privacy.mode",
            f"got {mode!r}; strategy={strategy.name} needs each agent's update alone, which "
            "privacy hides or changes: use strategy=mean, weighted, or fedadam over either",
        )
    if averaging == "weighted" and mode in ("dp", "dp_secagg"):
        raise ConfigError(
            "privacy.mode",
            f"got {mode!r} with weights by trajectories: one agent's weight would be unbounded "
            "in the sum DP protects; use strategy=mean (or fedadam over it)",
        )
    if ROUND_POLICIES.get(run.server.round_policy).asynchronous:
        raise ConfigError(
            "server.round_policy",
            f"got {run.server.round_policy!r}; privacy.mode={mode} accounts and masks "
            "synchronous rounds: use wait_all or deadline",
        )
    if mode in ("secagg", "dp_secagg"):
        _check_secure_rounds(run)
    return PrivateRounds(run, weighted=averaging == "weighted")


def _check_secure_rounds(run: RunConfig) -> None:
    """Every round size the run expects can meet ``privacy.secagg``'s own tolerance: a
    threshold or neighbour count that cannot is refused before anything starts."""
    participation = run.strategy.participation
    sizes = {run.agents.num_agents}
    if participation.mode == "uniform" and participation.per_round is not None:
        sizes = {participation.per_round}
    secagg = run.privacy.secagg
    key = (
        "privacy.secagg.threshold"
        if secagg.threshold is not None
        else "privacy.secagg.neighbours"
        if secagg.neighbours is not None
        else "privacy.secagg.corruption"
    )
    for size in sorted(sizes):
        try:
            round_plan(secagg, size)
        except GraphError as error:
            raise ConfigError(key, str(error)) from None


def _check_round_policy(run: RunConfig, strategy: Strategy[Any], *, distributed: bool) -> None:
    """What ``server.round_policy=buffered`` cannot combine with (config.py checks the keys'
    own ranges)."""
    if not ROUND_POLICIES.get(run.server.round_policy).asynchronous:
        return
    if run.strategy.participation.mode != "all":
        raise ConfigError(
            "strategy.participation.mode",
            f"got {run.strategy.participation.mode!r}; server.round_policy=buffered keeps every "
            "agent busy (each restarts as soon as it is aggregated): use 'all'",
        )
    if not strategy.buffered:
        raise ConfigError(
            "server.round_policy",
            f"got {run.server.round_policy!r}; strategy={strategy.name} aggregates every "
            "agent's update at one θ̃ each round, not buffered updates of different ages: "
            "use wait_all",
        )
    if distributed and agents_per_host(run) > 1:
        raise ConfigError(
            "agents.per_host",
            f"got {run.agents.per_host}; server.round_policy=buffered takes one agent per "
            "process (one Train to a host carries one round index): use agents.per_host=1",
        )


# --- checkpoints --------------------------------------------------------------------------------


class CheckpointSink:
    """Write a checkpoint after every round: θ̃, the config, the progress and ``counters()``;
    with ``checkpoint.every`` N every N-th round's is also kept, with ``checkpoint.keep_best``
    the best evaluation's so far (mean return over the agents) as ``best.safetensors``."""

    def __init__(
        self,
        run: RunConfig,
        directory: Path,
        progress: RunProgress,
        counters: Callable[[], dict[str, int]],
    ) -> None:
        self.run, self.directory, self.progress, self.counters = run, directory, progress, counters
        self.settings = to_dict(run)
        self.best: tuple[int, float] | None = None
        """The best checkpoint's round and mean evaluation return (``checkpoint.keep_best``)."""
        if run.checkpoint.keep_best:
            self.best = _best_so_far(directory)

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        progress = self.progress
        checkpoint = Checkpoint(
            round=record.round,
            theta=theta,
            config=self.settings,
            metrics_lines=record.round,
            state={
                "trajectories_per_agent": progress.trajectories_per_agent,
                "elapsed_s": progress.elapsed_s,
                "counters": self.counters(),
                **({"plan": progress.plan_state} if progress.plan_state else {}),
                **({"privacy": progress.privacy_state} if progress.privacy_state else {}),
            },
            strategy=progress.strategy_state,
            schedule=progress.schedule_state,
        )
        try:
            save_checkpoint(self.directory, checkpoint, keep_every=self.run.checkpoint.every)
            if self.run.checkpoint.keep_best and record.eval:
                value = mean_return(record.eval)
                if self.best is None or value > self.best[1]:
                    save_best(self.directory, checkpoint, value)
                    self.best = (record.round, value)
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write the checkpoint of round {record.round} in {self.directory}: "
                f"{error.strerror or error}; the newest complete checkpoint is kept"
            ) from None

    def summary(self) -> dict[str, Any]:
        """summary.json's ``best`` (with ``checkpoint.keep_best``): its round and return."""
        if not self.run.checkpoint.keep_best:
            return {}
        if self.best is None:
            return {"best": None}
        return {"best": {"round": self.best[0], "return_mean": self.best[1]}}


def _best_so_far(directory: Path) -> tuple[int, float] | None:
    """A resumed run's best checkpoint: its round and return; None where there is none (a
    damaged one is replaced by the next evaluation)."""
    try:
        best = best_checkpoint(directory)
    except CheckpointError as error:
        logger.warning("the best checkpoint is replaced at the next evaluation: %s", error)
        return None
    if best is None or BEST_RETURN not in best.state:
        return None
    return best.round, float(best.state[BEST_RETURN])


def resume_checkpoint(
    run: RunConfig, run_dir: RunDirectory, strategy: Strategy[Any]
) -> Checkpoint | None:
    """The newest valid checkpoint a resume of ``run`` continues from, after every check a
    resume makes (the config, rounds, the strategy's state, metrics.jsonl up to the
    checkpoint), with nothing changed: entry points ask it before they start anything. None
    for a run stopped before its first round was saved (no round in metrics.jsonl, nothing in
    checkpoints/): it starts from round 0, and nothing is lost."""
    out_dir = run_dir.path
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    if checkpoint is None:
        if not run_dir.holds_rounds():
            return None
        raise ConfigError(
            "resume",
            f"no valid checkpoint in {out_dir / 'checkpoints'}, but the run has recorded "
            "rounds: restore a checkpoint, or start a new run in another directory",
        )
    changed = fixed_difference(checkpoint.config, to_dict(run))
    if changed is not None:
        message = str(changed).split(": ", 1)[1]
        raise ConfigError(changed.key, f"{message} (the checkpoint in {out_dir})")
    planned = int(checkpoint.config.get("rounds", checkpoint.round))
    if run.rounds < planned:
        raise ConfigError(
            "rounds",
            f"got {run.rounds}, but the run in {out_dir} has rounds={planned} (checkpointed at "
            f"round {checkpoint.round}); a resume may keep or raise rounds, never lower them",
        )
    if strategy.state().scalars and not checkpoint.strategy.scalars:
        raise ConfigError(
            "resume",
            f"the checkpoint holds no state of strategy {strategy.name!r}; it cannot be resumed",
        )
    if ROUND_POLICIES.get(run.server.round_policy).asynchronous and checkpoint.schedule is None:
        raise ConfigError(
            "server.round_policy",
            f"got {run.server.round_policy!r}, but the checkpoint was written by synchronous "
            "rounds (it holds no buffered schedule); resume with the run's own round policy",
        )
    run_dir.checked_metrics(checkpoint.metrics_lines)
    return checkpoint


def resume_point(
    run: RunConfig, run_dir: RunDirectory, strategy: Strategy[Any]
) -> tuple[torch.Tensor, RunProgress, dict[str, int]] | None:
    """θ̃, the run's progress and its counters from the newest valid checkpoint. Everything is
    checked first (:func:`resume_checkpoint`); only then is metrics.jsonl cut back to the
    checkpoint. None for a run stopped before its first round was saved: it starts from
    round 0."""
    out_dir = run_dir.path
    checkpoint = resume_checkpoint(run, run_dir, strategy)
    if checkpoint is None:
        logger.warning("resuming %s: no round was saved, so it starts from round 0", out_dir)
        return None
    kept = run_dir.checked_metrics(checkpoint.metrics_lines)
    write_atomic(run_dir.metrics, "".join(line + "\n" for line in kept).encode())
    logger.warning("resuming %s after round %d", out_dir, checkpoint.round)
    progress = RunProgress(
        next_round=checkpoint.round + 1,
        trajectories_per_agent=float(checkpoint.state.get("trajectories_per_agent", 0.0)),
        elapsed_s=float(checkpoint.state.get("elapsed_s", 0.0)),
        strategy_state=checkpoint.strategy,
        plan_state=dict(checkpoint.state.get("plan", {})),
        privacy_state=dict(checkpoint.state.get("privacy", {})),
        schedule_state=checkpoint.schedule,
    )
    counters = checkpoint.state.get("counters", {})
    return checkpoint.theta, progress, {k: int(v) for k, v in dict(counters).items()}


# --- the parts of a run -------------------------------------------------------------------------


def evaluation_json(stats: EvaluationStats, *, has_goal: bool) -> dict[str, Any]:
    """An evaluation as summary.json holds it: ``success_rate`` null where the environment has
    no goal (a rate of 0 would read as a failed task)."""
    values = stats.to_json()
    if not has_goal:
        values["success_rate"] = None
    return values


@dataclass
class LastEvaluation:
    """The last round's evaluation, as the rounds go (for summary.json and the final table)."""

    round: int | None = None
    eval: dict[str, EvaluationStats] | None = None

    def __call__(self, record: RoundRecord, _: torch.Tensor) -> None:
        if record.eval:
            self.round, self.eval = record.round, record.eval


@dataclass(kw_only=True)
class Assembly:
    """A checked run's parts, ready for an agent pool."""

    checked: CheckedRun
    theta: torch.Tensor
    """θ̃ to start from: θ̃_0, or the checkpoint's."""
    progress: RunProgress
    counters: dict[str, int]
    """The pool's counters a checkpoint kept (rejected messages, deaths, ...)."""
    run_dir: RunDirectory | None
    sinks: list[RoundCallback]
    """Called after every round, in order: the run directory's, then the caller's."""
    last: LastEvaluation = field(default_factory=LastEvaluation)
    pool: AgentPool | None = None
    stopped_early: int | None = None
    """The round whose evaluation reached ``eval.stop_at``, where one did."""
    checkpoints: CheckpointSink | None = None
    """With a run directory: its checkpoints (the best one's round and return)."""
    _closers: list[Callable[[], None]] = field(default_factory=list)

    @property
    def run(self) -> RunConfig:
        return self.checked.run

    @property
    def strategy(self) -> Strategy[Any]:
        return self.checked.strategy

    def pool_counters(self) -> dict[str, int]:
        return self.pool.counters() if self.pool is not None else {}

    def coordinator(
        self, pool: AgentPool, *, buffered: type[BufferedCoordinator] = BufferedCoordinator
    ) -> Coordinator:
        """The round loop over ``pool``: ``buffered`` (the kind that reaches the pool's agents)
        with ``server.round_policy=buffered``, else the synchronous one."""
        self.pool = pool
        asynchronous = ROUND_POLICIES.get(self.run.server.round_policy).asynchronous
        kind = buffered if asynchronous else Coordinator
        return kind(
            run=self.run,
            pool=pool,
            strategy=self.strategy,
            theta=self.theta,
            progress=self.progress,
            on_round=self.sinks,
            privacy=self.checked.privacy,
        )

    def run_rounds(
        self, pool: AgentPool, *, buffered: type[BufferedCoordinator] = BufferedCoordinator
    ) -> torch.Tensor:
        """Every round left, over ``pool`` (up to one that reached ``eval.stop_at``); the final
        θ̃."""
        coordinator = self.coordinator(pool, buffered=buffered)
        self.theta = coordinator.run_rounds()
        self.stopped_early = coordinator.stopped_early
        return self.theta

    def finish(self, agent_ids: Sequence[str], **extra: Any) -> dict[str, Any]:
        """``summary.json`` (with a run directory): the last evaluation, the pool's counters,
        ``extra`` and every agent's environment variant; returned as written."""
        last = self.last
        variants = {
            agent: {"gamma": discount(self.run, variant), **variant.params}
            for agent, variant in zip(agent_ids, run_variants(self.run), strict=True)
        }
        has_goal = self.checked.first.has_goal
        summary = {
            "rounds": self.run.rounds,
            "final_eval_round": last.round,
            "eval": {a: evaluation_json(e, has_goal=has_goal) for a, e in last.eval.items()}
            if last.eval
            else None,
            **self._stopped_early(),
            **(self.checkpoints.summary() if self.checkpoints is not None else {}),
            **self.pool_counters(),
            **extra,
            **({"privacy": self.checked.privacy.summary()} if self.checked.privacy else {}),
            "variants": variants,
        }
        if self.run_dir is not None:
            path = self.run_dir.path / "summary.json"
            write_atomic(path, json.dumps(summary, indent=2).encode())
        return summary

    def _stopped_early(self) -> dict[str, Any]:
        """summary.json's ``stopped_early`` (with ``eval.stop_at``): the round whose evaluation
        reached the target, or null when the run went to ``rounds``."""
        target = self.run.eval.stop_at
        if target is None:
            return {}
        if self.stopped_early is None:
            return {"stopped_early": None}
        return {"stopped_early": {"round": self.stopped_early, "stop_at": target}}

    def close(self) -> None:
        """Close the sinks (metrics.jsonl, TensorBoard)."""
        while self._closers:
            self._closers.pop()()


def assemble(
    checked: CheckedRun,
    *,
    run_dir: RunDirectory | None = None,
    callbacks: Sequence[RoundCallback] = (),
) -> Assembly:
    """The parts of ``checked``'s run: θ̃ and its progress (from the newest checkpoint in
    ``run_dir`` when the run resumes), and with ``run_dir`` its config.json, metrics.jsonl,
    checkpoints and TensorBoard events; ``callbacks`` after those. Close it when done."""
    run = checked.run
    theta, progress = checked.initial_theta, RunProgress()
    counters: dict[str, int] = {}
    attackers = attacking_agents(run)
    if attackers:
        shown = ", ".join(map(str, attackers[:20])) + (" …" if len(attackers) > 20 else "")
        logger.warning(
            "attack=%s: agents %s attack (attack.agents); metrics.jsonl and the final table "
            "mark them",
            run.attack.kind,
            shown,
        )
    resuming = False
    if run.resume:
        if run_dir is None:
            raise ConfigError("resume", "resuming needs the run directory: pass out_dir")
        point = resume_point(run, run_dir, checked.strategy)
        if point is not None:
            theta, progress, counters = point
            resuming = True
    assembly = Assembly(
        checked=checked,
        theta=theta,
        progress=progress,
        counters=counters,
        run_dir=run_dir,
        sinks=[],
    )
    if run_dir is not None:
        out_dir = run_dir.path
        if checked.privacy is not None:  # each round accounted here before θ̃ leaves
            checked.privacy.keep_journal(out_dir / "checkpoints", resuming=resuming)
        write_atomic(out_dir / "config.json", json.dumps(to_dict(run), indent=2).encode())
        metrics = MetricsWriter(run_dir.metrics, marks=record_marks(run))
        assembly._closers.append(metrics.close)
        assembly.checkpoints = CheckpointSink(
            run, out_dir / "checkpoints", progress, assembly.pool_counters
        )
        assembly.sinks += [metrics, assembly.checkpoints]
        board = tensorboard_sink(run, out_dir, first_round=progress.next_round, theta=theta)
        progress_csv = ProgressCsv(
            out_dir / PROGRESS_NAME,
            first_round=progress.next_round,
            has_goal=checked.first.has_goal,
        )
        weights_and_biases = wandb_sink(run, out_dir, theta)
        for sink in (board, progress_csv, weights_and_biases):
            if sink is not None:
                assembly._closers.append(sink.close)
                assembly.sinks.append(sink)
    assembly.sinks += [assembly.last, *callbacks]
    return assembly


def run_in_process(run: RunConfig, *, on_round: Sequence[RoundCallback] = ()) -> torch.Tensor:
    """Run the whole federation of ``run`` here, its K agents as one group on this thread
    (no run directory: ``on_round`` sees every round); the final θ̃_T."""
    validate_run(run)  # a config made in code, not composed: checked as the CLI checks it
    assembly = assemble(check_run(run, distributed=False), callbacks=on_round)
    pool = make_in_process_pool(run)
    try:
        return assembly.run_rounds(pool)
    finally:
        pool.close()
        assembly.close()
