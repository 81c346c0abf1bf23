"""The Theorem 1 planner against the alternatives at the same emulated-time budget.

For each setting and seed: the planner's constants come from the seeded pilot ``fedhpg-plan``
runs (``server/commands/plan.py``), its cost per trajectory from the counted clock's full-horizon
price. Every alternative then runs in process on the counted, virtual clock (emulated time is priced
from counted work: identical on any machine, under any load) until the unified policy reaches
the threshold or its emulated time (the sum over rounds of the slowest agent's emulated round
time) passes the budget. Recorded: emulated seconds and trajectories per agent at the first
evaluation at or past the threshold; a run that never reaches it is censored at the budget.

Alternatives (τ_k = local_iters, B_k = batch_size):
- ``uniform``: the algorithm's default for every agent (B = 10, τ = 2);
- ``speed-proportional``: B_k = max(2, round(20 × speed_k / fastest)), τ_k = 1;
- ``paper Fig. 1``: B = (2, 5, 10, 20) tiled over the agents, τ = 2;
- ``paper Fig. 2``: B = 5, τ = (5, 5, 6, 6) tiled;
- ``planner``: ``plan_budgets`` with the pilot's constants, for the budget;
- ``planner, budget/10``: the same for a tenth of the budget (run under the full budget).

``python -m benchmarks.planner [--settings gridworld-demo,...] [--seeds 5]`` writes
``benchmarks/results/planner.json``, ``docs/figures/planner.png`` and prints the table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks import results_file
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.device import device_for
from fedhpg.common.learning.planning import Constants, Limits, plan_budgets
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.commands.plan import horizon_seconds_per_trajectory, round_overhead_s, run_pilot
from fedhpg.server.commands.plot_stats import stratified_bootstrap_ci
from fedhpg.server.coordinator import RoundRecord

RESULTS = Path("benchmarks/results/planner.json")
FIGURE = Path("docs/figures/planner.png")
COUNTED = ["agents.clock=counted", "agents.virtual_clock=true"]
SPREAD_SPEEDS = [1.0, 0.464, 0.215, 0.1]  # 10×, geometric
CARTPOLE_SPEEDS = "{lognormal: {median: 1, sigma: 0.7}, min: 0.1, max: 4}"
ALTERNATIVES = (
    "uniform",
    "speed-proportional",
    "paper Fig. 1",
    "paper Fig. 2",
    "planner",
    "planner, budget/10",
)
TIGHT = 10.0
"""The second planner plans for a tenth of the budget (and runs under the full one): how the
plan moves with the budget it is given."""


def _gridworld_solved(record: RoundRecord) -> bool:
    return bool(record.eval) and min(e.success_rate for e in record.eval.values()) >= 0.9


def _cartpole_solved(record: RoundRecord) -> bool:
    if not record.eval:
        return False
    return float(np.mean([e.return_mean for e in record.eval.values()])) >= 475.0


@dataclass(frozen=True)
class Setting:
    name: str
    overrides: list[str]
    solved: Callable[[RoundRecord], bool]
    threshold: str
    max_return: float
    budget_s: float
    rounds_cap: int


SETTINGS = {
    "gridworld-demo": Setting(
        "GridWorld K=4, speeds 1/1/0.5/0.25 (demo)",
        [*COUNTED, "eval.every=1", "eval.episodes=50"],
        _gridworld_solved,
        "greedy success ≥ 0.9 in all 4 grids",
        1.0,
        20.0,
        1000,
    ),
    "gridworld-spread": Setting(
        "GridWorld K=4, speeds 1/0.46/0.22/0.1 (10× spread)",
        [
            *COUNTED,
            "eval.every=1",
            "eval.episodes=50",
            f"agents.speeds={SPREAD_SPEEDS}",
            f"agents.step_delays_s={[round(2e-4 / s, 6) for s in SPREAD_SPEEDS]}",
        ],
        _gridworld_solved,
        "greedy success ≥ 0.9 in all 4 grids",
        1.0,
        20.0,
        1000,
    ),
    "cartpole-10": Setting(
        "CartPole K=10 from a population (lognormal speeds)",
        [
            *COUNTED,
            "agents=homogeneous10",
            "env=cartpole",
            "agents.population.kind=drawn",
            f"+agents.population.draw.speed={CARTPOLE_SPEEDS}",
            "eval.every=2",
            "eval.episodes=5",
        ],
        _cartpole_solved,
        "mean greedy return ≥ 475 over the agents",
        500.0,
        60.0,
        400,
    ),
    "cartpole-100": Setting(
        "CartPole K=100, the population group's speeds and step delays",
        [
            *COUNTED,
            "agents=population",
            "env=cartpole",
            # The group also draws budgets; those are what the alternatives choose here.
            *(
                f"~agents.population.draw.{name}"
                for name in ("batch_size", "local_iters", "inner_steps", "mini_batch_size")
            ),
            "eval.every=2",
            "eval.episodes=2",
        ],
        _cartpole_solved,
        "mean greedy return ≥ 475 over the agents",
        500.0,
        60.0,
        400,
    ),
}


def alternatives(
    run: RunConfig, plans: dict[str, tuple[list[int], list[int], float]]
) -> dict[str, Any]:
    k = run.agents.num_agents
    speeds = [device_for(run, i).speed for i in range(k)]

    def tiled(values: list[int]) -> list[int]:
        return [values[i % len(values)] for i in range(k)]

    return {
        "uniform": ([10] * k, [2] * k),
        "speed-proportional": (
            [max(2, round(20 * s / max(speeds))) for s in speeds],
            [1] * k,
        ),
        "paper Fig. 1": (tiled([2, 5, 10, 20]), [2] * k),
        "paper Fig. 2": ([5] * k, tiled([5, 5, 6, 6])),
        **{name: (b, t) for name, (b, t, _) in plans.items()},
    }


class _Reached(Exception):
    pass


@dataclass
class Outcome:
    setting: str
    alternative: str
    seed: int
    batch_sizes: list[int]
    local_iters: list[int]
    reached: bool
    emulated_s: float
    trajectories_per_agent: float
    rounds: int
    planned_bound: float | None
    wall_s: float


def _run_to_threshold(
    setting: Setting, seed: int, name: str, batches: list[int], iters: list[int]
) -> Outcome:
    run = compose(
        [
            *setting.overrides,
            f"seed={seed}",
            f"rounds={setting.rounds_cap}",
            f"agents.budget.batch_size={batches}",
            f"agents.budget.local_iters={iters}",
        ]
    )
    spent = [0.0]
    state: dict[str, Any] = {}

    def watch(record: RoundRecord, _: torch.Tensor) -> None:
        spent[0] += max(record.result.stats.emulated_s)
        state.update(rounds=record.round, traj=record.trajectories_per_agent)
        if setting.solved(record):
            state["reached"] = True
            raise _Reached
        if spent[0] >= setting.budget_s:
            raise _Reached

    started = time.perf_counter()
    with contextlib.suppress(_Reached):  # the watch ends the run at the threshold
        run_in_process(run, on_round=[watch])
    # A threshold first met in a round that ends past the budget was not met within it.
    reached = bool(state.get("reached")) and spent[0] <= setting.budget_s
    return Outcome(
        setting=setting.name,
        alternative=name,
        seed=seed,
        batch_sizes=batches,
        local_iters=iters,
        reached=reached,
        emulated_s=spent[0] if reached else setting.budget_s,
        trajectories_per_agent=float(state.get("traj", 0.0)),
        rounds=int(state.get("rounds", 0)),
        planned_bound=None,
        wall_s=time.perf_counter() - started,
    )


def plans_for(setting: Setting, seed: int) -> dict[str, tuple[list[int], list[int], float]]:
    run = compose([*setting.overrides, f"seed={seed}"])
    pilot = run_pilot(run, 4)
    constants = Constants(
        gap=max(setting.max_return - pilot.initial_return, 0.0),
        step_size=run.algo.step_size,
        smoothness=pilot.smoothness,
        second_moment=pilot.second_moment,
        variances=pilot.variances,
    )
    seconds = horizon_seconds_per_trajectory(run)
    overhead = round_overhead_s(run)
    plans = {}
    for name, budget in (
        ("planner", setting.budget_s),
        ("planner, budget/10", setting.budget_s / TIGHT),
    ):
        plan = plan_budgets(
            constants=constants,
            seconds_per_trajectory=seconds,
            overhead_s=overhead,
            total_s=budget,
            limits=Limits(batch_max=64, local_iters_max=8),
        )
        plans[name] = (list(plan.batch_sizes), list(plan.local_iters), plan.bound)
    return plans


def measure(
    setting_key: str, seeds: list[int], save: Callable[[Outcome], None] = lambda _: None
) -> list[Outcome]:
    """Every alternative on every seed; ``save`` is called after each run (long settings
    keep what they measured if stopped)."""
    setting = SETTINGS[setting_key]
    outcomes = []
    for seed in seeds:
        plans = plans_for(setting, seed)
        run = compose([*setting.overrides, f"seed={seed}"])
        for name, (b, t) in alternatives(run, plans).items():
            outcome = _run_to_threshold(setting, seed, name, b, t)
            if name in plans:
                outcome.planned_bound = plans[name][2]
            logging.getLogger(__name__).warning(
                "%s seed %d %s: reached=%s emulated %.3g s, %.0f traj/agent (%.1f s wall)",
                setting_key,
                seed,
                name,
                outcome.reached,
                outcome.emulated_s,
                outcome.trajectories_per_agent,
                outcome.wall_s,
            )
            outcomes.append(outcome)
            save(outcome)
    return outcomes


def _mean_ci(values: list[float]) -> tuple[float, float, float]:
    data = np.asarray(values, dtype=float)
    if len(data) < 2:
        return float(data.mean()), float(data.mean()), float(data.mean())
    low, high = stratified_bootstrap_ci(data[:, None], "mean")
    return float(data.mean()), float(low), float(high)


def _budgets(values: list[int]) -> str:
    """A budget list as the table shows it: whole up to 10 agents, else its range."""
    if len(values) <= 10:
        return str(values)
    return f"{min(values)}–{max(values)} over {len(values)}"


def table(outcomes: list[Outcome]) -> str:
    lines = [
        "| setting | budgets | B_k (seed 0) | τ_k (seed 0) | reached | emulated s to threshold, "
        "mean [95% CI] | trajectories per agent to threshold, mean [95% CI] |",
        "|---|---|---|---|---|---|---|",
    ]
    for setting in dict.fromkeys(o.setting for o in outcomes):
        for name in ALTERNATIVES:
            rows = [o for o in outcomes if o.setting == setting and o.alternative == name]
            if not rows:
                continue
            e = _mean_ci([o.emulated_s for o in rows])
            t = _mean_ci([o.trajectories_per_agent for o in rows])
            first = rows[0]
            lines.append(
                f"| {setting} | {name} | {_budgets(first.batch_sizes)} | "
                f"{_budgets(first.local_iters)} | "
                f"{sum(o.reached for o in rows)}/{len(rows)} | {e[0]:.2f} [{e[1]:.2f}, {e[2]:.2f}]"
                f" | {t[0]:.0f} [{t[1]:.0f}, {t[2]:.0f}] |"
            )
    return "\n".join(lines)


def figure(outcomes: list[Outcome], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = list(dict.fromkeys(o.setting for o in outcomes))
    fig, axes = plt.subplots(2, len(settings), figsize=(5 * len(settings), 7), squeeze=False)
    for column, setting in enumerate(settings):
        for row, (field, label) in enumerate(
            [("emulated_s", "emulated s to threshold"), ("trajectories_per_agent", "traj/agent")]
        ):
            ax = axes[row][column]
            names = [n for n in ALTERNATIVES if any(o.alternative == n for o in outcomes)]
            for x, name in enumerate(names):
                rows = [o for o in outcomes if o.setting == setting and o.alternative == name]
                values = [getattr(o, field) for o in rows]
                mean, low, high = _mean_ci(values)
                ax.bar(x, mean, color="C3" if name.startswith("planner") else "C0")
                ax.errorbar(x, mean, yerr=[[mean - low], [high - mean]], color="k", capsize=4)
                ax.scatter([x] * len(values), values, s=8, color="k", zorder=3)
            ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
            ax.set_ylabel(label)
            if row == 0:
                ax.set_title(setting, fontsize=9)
    fig.suptitle("Theorem 1 planner vs alternatives: mean, 95% bootstrap CI, seeds as dots")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", default="gridworld-demo,gridworld-spread")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument(
        "--table-only", action="store_true", help="table and figure from the saved results"
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    torch.set_num_threads(1)
    previous = json.loads(RESULTS.read_text()) if RESULTS.exists() else []
    keys = args.settings.split(",")
    names = {SETTINGS[k].name for k in keys}
    outcomes = [Outcome(**o) for o in previous if args.table_only or o["setting"] not in names]
    if args.table_only:
        figure(outcomes, FIGURE)
        print(table(outcomes))
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)

    def save(outcome: Outcome) -> None:
        outcomes.append(outcome)
        RESULTS.write_text(json.dumps([asdict(o) for o in outcomes], indent=1))

    for key in keys:
        measure(key, list(range(args.seeds)), save)
    figure(outcomes, FIGURE)
    print(table(outcomes))
    print(f"\n{RESULTS}, {FIGURE}")
    if len(outcomes) != sum(1 for o in outcomes if o.setting in names):
        print(f"{RESULTS} holds other settings' earlier outcomes: the table is not stored")
        return
    summary = (
        "Each set of budgets on each setting at the same emulated-time budget: how many seeds "
        "reach the threshold, and the emulated time and trajectories it takes."
    )
    results_file.refresh(
        "planner",
        [results_file.table_from_markdown(table(outcomes), summary)],
        results_file.command_line("benchmarks.planner"),
    )


if __name__ == "__main__":
    main()
