"""``fedhpg-plan``: choose every agent's (B_k, τ_k) by Theorem 1 for a run's config and an
emulated-time budget, and print the plan, its bound and the overrides that run it.

The constants come from a seeded pilot: ``--pilot-rounds`` in-process rounds of the same config
with ``algo.bound_estimates=true`` and τ_k = 2 (so every agent estimates L̂), from θ̃_0. σ_k² is
agent k's mean σ̂_k² over the pilot, M the largest M̂_k, L the largest L̂_k (secants are lower
estimates of the supremum Assumption 4 asks for, so the largest is the least optimistic). The
gap J(θ*) − J(θ_0) is ``--max-return`` minus the pilot's first-round mean training return;
``--max-return`` defaults to the horizon H (a reward of at most 1 per step, exact for CartPole,
an over-estimate for GridWorld whose return is at most 1).

Each agent's seconds per trajectory: with ``--cost horizon`` (the default on the counted clock)
the counted clock's price of a full-horizon trajectory, H × ((step_cost + grad_cost × d/10⁴) /
speed + step_delay), an upper bound, so the planned round times are never exceeded; with
``--cost pilot`` the pilot's observed emulated seconds per trajectory (the measured clock's
only option; the pilot also computes the bound estimates' extra gradients, so this is a little
above a plain round's cost, and at θ̃_0's episode lengths). The per-round overhead is the
counted clock's two messages (``common/heterogeneity/device.py``).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NoReturn

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.vocabularies import CLOCKS
from fedhpg.common.heterogeneity.device import device_for
from fedhpg.common.heterogeneity.variants import training_horizon, variant_of
from fedhpg.common.learning.components import agent_profile, resolve_algorithm
from fedhpg.common.learning.planning import (
    Constants,
    Limits,
    agent_round_seconds,
    plan_budgets,
    score_budgets,
)
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import (
    EXIT_USAGE,
    compose,
    fail,
    limit_threads,
    repeated_key,
    setup_logging,
    version_text,
)
from fedhpg.server.commands.api import resolve_config
from fedhpg.server.commands.api import run as run_federation
from fedhpg.server.replan import round_overhead_s

if TYPE_CHECKING:
    from fedhpg.common.learning.planning import Plan

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Pilot:
    """What the pilot measured."""

    variances: tuple[float, ...]
    second_moment: float
    smoothness: float
    initial_return: float
    seconds_per_trajectory: tuple[float, ...]
    """Observed: emulated seconds of the pilot's rounds, less the messages, per trajectory."""


def pilot_config(run: RunConfig, rounds: int) -> RunConfig:
    """The pilot's run: the same federation, bound estimates on, τ_k = 2, no sleeping."""
    batch = [max(2, b) for b in run.agents.budget.get("batch_size", [10])]
    return resolve_config(
        run,
        [
            f"rounds={rounds}",
            "algo.bound_estimates=true",
            "agents.budget.local_iters=[2]",
            f"agents.budget.batch_size={batch}",
            "agents.virtual_clock=true",
            f"eval.every={rounds + 1}",
            "eval.episodes=1",
            "server.out_dir=null",
            "server.tensorboard=false",
            "resume=null",
        ],
    )


def run_pilot(run: RunConfig, rounds: int) -> Pilot:
    records = run_federation(pilot_config(run, rounds)).records
    k = run.agents.num_agents
    per_agent: dict[int, list[float]] = {i: [] for i in range(k)}
    spent = [0.0] * k
    trajectories = [0] * k
    second_moments, secants = [], []
    overhead = round_overhead_s(run)
    for record in records:
        for agent in record["agents"]:
            index = int(agent["index"])
            per_agent[index].append(float(agent["bound_variance"]))
            second_moments.append(float(agent["bound_second_moment"]))
            if "bound_smoothness" in agent:
                secants.append(float(agent["bound_smoothness"]))
            spent[index] += float(agent["emulated_s"]) - overhead[index]
            trajectories[index] += int(agent["trajectories"])
    first = records[0]["agents"]
    return Pilot(
        variances=tuple(statistics.fmean(per_agent[i]) for i in range(k)),
        second_moment=max(second_moments),
        smoothness=max(secants, default=0.0),
        initial_return=statistics.fmean(float(a["train_return"]) for a in first),
        seconds_per_trajectory=tuple(spent[i] / trajectories[i] for i in range(k)),
    )


def observed_seconds_per_trajectory(
    run: RunConfig, records: Sequence[dict[str, object]], *, per: str = "trajectories"
) -> list[float]:
    """Each agent's emulated seconds per trajectory (``per="env_steps"``: per env step) over
    the given round records (``metrics.jsonl`` lines), less its messages: the speed a planner
    re-planning every few rounds observes. An agent absent from every record is an error."""
    overhead = round_overhead_s(run)
    spent = [0.0] * run.agents.num_agents
    work = [0] * run.agents.num_agents
    for record in records:
        agents = record["agents"]
        assert isinstance(agents, list)
        for agent in agents:
            index = int(agent["index"])
            spent[index] += float(agent["emulated_s"]) - overhead[index]
            work[index] += int(agent[per])
    missing = [k for k, n in enumerate(work) if n == 0]
    if missing:
        raise ValueError(f"no {per} observed for agents {missing}")
    return [s / n for s, n in zip(spent, work, strict=True)]


def horizon_seconds_per_trajectory(run: RunConfig, round_index: int = 1) -> list[float]:
    """The counted clock's price of a full-horizon trajectory on each agent's device at the
    speed its schedule gives in ``round_index``: an upper bound on any trajectory's."""
    params = initial_theta(variant_of(run, 0), run).numel()
    seconds = []
    for k in range(run.agents.num_agents):
        device = device_for(run, k)
        horizon = training_horizon(run, variant_of(run, k))
        compute = device.compute_s(0.0, horizon, horizon, params)
        seconds.append(compute / device.speed_at(round_index) + horizon * device.step_delay_s)
    return seconds


def configured_budgets(run: RunConfig) -> tuple[list[int], list[int]]:
    budgets = [agent_profile(run, k).budget for k in range(run.agents.num_agents)]
    return [int(b.batch_size) for b in budgets], [int(b.local_iters) for b in budgets]


def overrides_line(plan: Plan) -> str:
    batches = ",".join(str(b) for b in plan.batch_sizes)
    iters = ",".join(str(t) for t in plan.local_iters)
    return (
        f"agents.budget.batch_size=[{batches}] agents.budget.local_iters=[{iters}] "
        f"rounds={plan.rounds}"
    )


def plan_table(plan: Plan, seconds_per_trajectory: Sequence[float]) -> str:
    lines = [
        f"{'agent':>5}  {'traj/s':>9}  {'B_k':>4}  {'tau_k':>5}  {'round s':>10}",
    ]
    for k, (b, t, r) in enumerate(
        zip(plan.batch_sizes, plan.local_iters, plan.agent_round_s, strict=True)
    ):
        lines.append(f"{k:>5}  {1 / seconds_per_trajectory[k]:>9.4g}  {b:>4}  {t:>5}  {r:>10.4g}")
    return "\n".join(lines)


def terms_text(label: str, plan: Plan) -> str:
    t = plan.terms
    return (
        f"{label}: bound {plan.bound:.4g} = optimisation {t.optimisation:.4g} + local drift "
        f"{t.local_drift:.4g} + variance {t.variance:.4g} + heterogeneity {t.heterogeneity:.4g}"
        f" ({plan.rounds} rounds of {plan.round_s:.4g} s; step-size condition "
        f"{'holds' if plan.step_size_ok else 'FAILS'})"
    )


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="fedhpg-plan",
        description=(
            "Choose every agent's batch size B_k and local iterations tau_k by Theorem 1 "
            "(eq. 7) for a run's config and an emulated-time budget. The remaining arguments "
            "are the key=value overrides fedhpg-run takes (docs/configuration.md, Choosing "
            "budgets)."
        ),
    )
    p.add_argument(
        "--budget-s",
        type=float,
        help="total emulated seconds (default: what the configured budgets take for `rounds`)",
    )
    p.add_argument("--pilot-rounds", type=int, default=4, help="rounds of the pilot (default 4)")
    p.add_argument("--gap", type=float, help="J(theta*) - J(theta_0) (default: see --max-return)")
    p.add_argument(
        "--max-return",
        type=float,
        help="largest return; the gap is this minus the pilot's initial return (default: H)",
    )
    p.add_argument("--smoothness", type=float, help="L instead of the pilot's largest secant")
    p.add_argument(
        "--cost",
        choices=("horizon", "pilot"),
        help="seconds per trajectory: counted-clock full horizon (default on the counted clock) "
        "or the pilot's observed (default on the measured clock)",
    )
    p.add_argument("--batch-min", type=int, default=2)
    p.add_argument("--batch-max", type=int, default=64)
    p.add_argument("--tau-max", type=int, default=8, help="largest tau_k (default 8)")
    p.add_argument("-V", "--version", action="version", version=version_text(p.prog).strip())
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args, overrides = parser().parse_known_args(sys.argv[1:] if argv is None else argv)
    stray = next((o for o in overrides if o.startswith("-")), None)
    if stray is not None:
        return fail(ConfigError(stray, "not an option; see fedhpg-plan --help"))
    repeated = repeated_key(overrides)
    if repeated is not None:
        return fail(repeated)
    setup_logging()
    # Imported past the argument check: a mistyped flag answers without torch's start-up.
    try:
        run = compose(overrides)
        limits = Limits(
            batch_min=args.batch_min, batch_max=args.batch_max, local_iters_max=args.tau_max
        )
        if args.budget_s is not None and not args.budget_s > 0:
            raise ConfigError("--budget-s", f"must be > 0 emulated seconds, got {args.budget_s:g}")
        if args.pilot_rounds < 1:
            raise ConfigError("--pilot-rounds", f"must be ≥ 1, got {args.pilot_rounds}")
        if not resolve_algorithm(run)[0].theorem1:
            raise ConfigError(
                "algo.name",
                f"the planner needs Theorem 1 (fedhpg); {run.algo.name}'s bound has constants "
                "no run can estimate (common/learning/planning.py, theorem2_shape)",
            )
    except ValueError as error:  # ConfigError is one
        return fail(error if isinstance(error, ConfigError) else ConfigError("plan", str(error)))
    counted = CLOCKS.get(run.agents.clock).counts_work
    cost = args.cost or ("horizon" if counted else "pilot")
    if cost == "horizon" and not counted:
        return fail(
            ConfigError("--cost", "'horizon' prices the counted clock: agents.clock=counted")
        )
    limit_threads()
    overhead = round_overhead_s(run)
    seconds: Sequence[float] = []
    if cost == "horizon":
        # Known before the pilot: a budget no round fits is a mistake found before any work.
        seconds = horizon_seconds_per_trajectory(run)
        smallest = max(limits.batch_min * c + o for c, o in zip(seconds, overhead, strict=True))
        if args.budget_s is not None and smallest > args.budget_s:
            return fail(
                ConfigError(
                    "--budget-s",
                    f"no round of batch_size ≥ {limits.batch_min} fits in {args.budget_s:g} "
                    f"emulated s (the slowest agent needs {smallest:g} s)",
                )
            )
    pilot = run_pilot(run, args.pilot_rounds)
    if cost == "pilot":
        seconds = pilot.seconds_per_trajectory
    smoothness = args.smoothness if args.smoothness is not None else pilot.smoothness
    if smoothness <= 0:
        return fail(
            ConfigError(
                "--smoothness",
                "the pilot measured no L > 0 (every secant was below its noise): give more "
                "--pilot-rounds or --smoothness",
            )
        )
    horizon = training_horizon(run, variant_of(run, 0))
    max_return = args.max_return if args.max_return is not None else float(horizon)
    gap = args.gap if args.gap is not None else max(max_return - pilot.initial_return, 0.0)
    constants = Constants(
        gap=gap,
        step_size=run.algo.step_size,
        smoothness=smoothness,
        second_moment=pilot.second_moment,
        variances=pilot.variances,
    )
    batches, iters = configured_budgets(run)
    try:
        configured_round_s = max(agent_round_seconds(iters, batches, seconds, overhead))
        total_s = args.budget_s if args.budget_s is not None else configured_round_s * run.rounds
        configured = score_budgets(
            constants=constants,
            seconds_per_trajectory=seconds,
            overhead_s=overhead,
            total_s=total_s,
            batch_sizes=batches,
            local_iters=iters,
        )
        plan = plan_budgets(
            constants=constants,
            seconds_per_trajectory=seconds,
            overhead_s=overhead,
            total_s=total_s,
            limits=limits,
        )
    except ValueError as error:
        return fail(ConfigError("--budget-s", str(error)))
    out = sys.stdout
    out.write(
        f"Theorem 1 plan for {total_s:.4g} emulated s ({cost} cost per trajectory); constants "
        f"from a {args.pilot_rounds}-round pilot: gap {gap:.4g}, step size {run.algo.step_size:g}"
        f", L {smoothness:.4g}, M {pilot.second_moment:.4g}, "
        f"sigma^2 {', '.join(f'{v:.3g}' for v in pilot.variances)}\n"
    )
    if run.algo.optimizer != "sgd" or run.strategy.name != "mean":
        out.write(
            "note: Theorem 1 assumes plain local SGD averaged by the mean; this run's "
            f"optimizer={run.algo.optimizer} strategy={run.strategy.name}\n"
        )
    out.write(plan_table(plan, seconds) + "\n")
    out.write(terms_text("planned", plan) + "\n")
    out.write(terms_text("configured", configured) + "\n")
    out.write(f"fedhpg-run {' '.join(overrides)} {overrides_line(plan)}".replace("  ", " ") + "\n")
    return 0


def entry() -> None:
    raise SystemExit(main())
