"""Asynchronous against synchronous rounds: emulated time and trajectories per agent until the
unified policy reaches a threshold, on heterogeneous devices (BENCHMARKS.md, Asynchronous
rounds).

Four round policies on the same set-ups: ``wait_all``, ``deadline`` (in process the deadline is
on the emulated clock: an update whose emulated time exceeds it is a straggler) and
``buffered`` with two buffer sizes M. In process, counted virtual clock
(``agents.clock=counted agents.virtual_clock=true``): every figure here is a function of the
seed alone, the same on any machine under any load, so this runs under ``nice`` beside
other work. Every seed's run is also checked bit-identical to a second run of it for the
first buffered policy of each set-up (``--no-repeat`` skips that). θ̃ is evaluated after the
same number of updates under every policy: every round, every K/M versions of a buffered run.

The emulated time of a synchronous round is its slowest aggregated update's (``wait_all``), or
the deadline where an update came too late (``deadline``); a buffered round's is the emulated
clock at its aggregation (``emulated_clock_s``). Trajectories per agent count every update
that arrived (a buffered run's stale updates included; a deadline's stragglers are not: their
agent processes are cancelled at the next round, so what they sampled is unknown).

``python -m benchmarks.async_rounds [--seeds 5] [--setups a,b]`` prints the table and writes
``benchmarks/results/async_rounds.json`` and ``docs/figures/async_rounds.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks import results_file
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.commands.plot_stats import stratified_bootstrap_ci
from fedhpg.server.coordinator import RoundRecord

RESULTS = Path("benchmarks/results/async_rounds.json")
FIGURE = Path("docs/figures/async_rounds.png")
COUNTED = ["agents.clock=counted", "agents.virtual_clock=true", "server.tensorboard=false"]


@dataclass(frozen=True)
class Setup:
    name: str
    title: str
    overrides: list[str]
    num_agents: int
    metric: str
    """'success' (the worst agent's greedy success rate) or 'return' (mean greedy return)."""
    threshold: float
    deadline_s: float
    """The deadline policy's round deadline, in emulated seconds."""
    buffers: tuple[int, int]
    budget_rounds: int
    """Synchronous rounds allowed; a buffered run gets the same number of updates."""
    cohort: int | None = None
    """Also ``wait_all`` with C = ``cohort`` agents drawn per round (participation uniform):
    as many updates per server step as the smaller buffer, synchronously."""


GEOMETRIC_10X = [round(10 ** (-k / 9), 4) for k in range(10)]  # 1 … 0.1, ten agents

SETUPS = {
    s.name: s
    for s in (
        Setup(
            name="gridworld-demo",
            title="GridWorld K=4, speeds 1/1/0.5/0.25 (the demo)",
            overrides=[],
            num_agents=4,
            metric="success",
            threshold=0.9,  # benchmarks/gridworld_threshold.py
            deadline_s=0.5,
            buffers=(1, 2),
            budget_rounds=100,
        ),
        Setup(
            name="gridworld-10x",
            title="GridWorld K=4, speeds 1/1/0.5/0.1 (10x spread)",
            overrides=[
                "agents.speeds=[1.0,1.0,0.5,0.1]",
                "agents.step_delays_s=[0.0002,0.0002,0.0004,0.002]",
            ],
            num_agents=4,
            metric="success",
            threshold=0.9,
            deadline_s=0.5,
            buffers=(1, 2),
            budget_rounds=100,
        ),
        Setup(
            name="cartpole-k10",
            title="CartPole K=10 (level 1), speeds 1 … 0.1 geometric",
            overrides=[
                "env=cartpole",
                "env.level=1.0",
                "agents=homogeneous10",
                f"agents.speeds=[{','.join(str(v) for v in GEOMETRIC_10X)}]",
                "eval.episodes=10",
            ],
            num_agents=10,
            metric="return",
            threshold=475.0,  # benchmarks/learning.py
            deadline_s=0.1,
            buffers=(3, 5),
            cohort=3,
            budget_rounds=80,
        ),
        Setup(
            name="cartpole-k100",
            title="CartPole K=100 (level 1), the drawn population's devices (agents=population)",
            overrides=["env=cartpole", "env.level=1.0", "agents=population", "eval.episodes=2"],
            num_agents=100,
            metric="return",
            threshold=475.0,
            deadline_s=0.5,
            buffers=(10, 25),
            budget_rounds=60,
        ),
    )
}
DEFAULT_SETUPS = ("gridworld-demo", "gridworld-10x", "cartpole-k10")
"""``cartpole-k100`` is run on its own (``make bench-async`` does, with 3 seeds): ~1 to 5 s a
round here."""


def policies(setup: Setup) -> dict[str, list[str]]:
    small, large = setup.buffers
    return {
        "wait_all": ["server.round_policy=wait_all"],
        "deadline": ["server.round_policy=deadline", f"server.round_deadline_s={setup.deadline_s}"],
        f"buffered M={small}": ["server.round_policy=buffered", f"server.buffer_size={small}"],
        f"buffered M={large}": ["server.round_policy=buffered", f"server.buffer_size={large}"],
        **(
            {}
            if setup.cohort is None
            else {
                f"wait_all C={setup.cohort}": [
                    "server.round_policy=wait_all",
                    "strategy.participation.mode=uniform",
                    f"strategy.participation.per_round={setup.cohort}",
                ]
            }
        ),
    }


@dataclass(frozen=True)
class Outcome:
    setup: str
    policy: str
    seed: int
    reached: bool
    emulated_s: float
    """At the threshold, or at the end of the budget when it was not reached."""
    trajectories_per_agent: float
    rounds: int
    final_metric: float
    mean_staleness: float
    stale_dropped: int
    wall_s: float
    repeat_identical: bool | None = None


class _Watch:
    """Follows a run's records: the emulated clock, the metric, the first threshold hit."""

    def __init__(self, setup: Setup, deadline_s: float | None) -> None:
        self.setup, self.deadline_s = setup, deadline_s
        self.clock = 0.0
        self.hit: tuple[float, float, int] | None = None
        self.metric = math.nan
        self.staleness: list[int] = []
        self.stale = 0
        self.figures: list[Any] = []

    def round_time(self, record: RoundRecord) -> float:
        slowest = max(record.result.stats.emulated_s, default=0.0)
        if self.deadline_s is not None and record.stragglers:
            return max(slowest, self.deadline_s)
        return slowest

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        if record.emulated_clock_s is not None:
            self.clock = record.emulated_clock_s
            self.staleness += record.staleness or []
            self.stale += len(record.stale)
        else:
            self.clock += self.round_time(record)
        self.figures.append((record.round, self.clock, record.trajectories_per_agent))
        if record.eval:
            evals = record.eval.values()
            if self.setup.metric == "success":
                self.metric = min(e.success_rate for e in evals)
            else:
                self.metric = float(np.mean([e.return_mean for e in evals]))
            if self.hit is None and self.metric >= self.setup.threshold:
                self.hit = (self.clock, record.trajectories_per_agent, record.round)
                raise _Reached


class _Reached(Exception):
    """Stops a run at its threshold (nothing after it is measured)."""


def one_run(setup: Setup, policy: str, seed: int) -> tuple[Outcome, list[Any], torch.Tensor]:
    chosen = policies(setup)[policy]
    buffered = "server.round_policy=buffered" in chosen
    size = setup.num_agents  # updates per server step
    if buffered or "C=" in policy:
        size = int(chosen[-1].split("=")[1])
    rounds = math.ceil(setup.budget_rounds * setup.num_agents / size)
    # Evaluations at the same number of updates (every K/M versions): the first evaluation at
    # or above a noisy threshold would otherwise come sooner the more often one looks.
    every = max(1, round(setup.num_agents / size))
    counts = [f"seed={seed}", f"rounds={rounds}", f"eval.every={every}"]
    run = compose([*COUNTED, *setup.overrides, *chosen, *counts])
    watch = _Watch(setup, setup.deadline_s if "deadline" in policy else None)
    theta = torch.empty(0)

    def keep(record: RoundRecord, current: torch.Tensor) -> None:
        nonlocal theta
        theta = current.clone()

    started = time.perf_counter()
    with contextlib.suppress(_Reached):
        run_in_process(run, on_round=[keep, watch])
    wall = time.perf_counter() - started
    last = watch.figures[-1]
    clock, trajectories, done = watch.hit if watch.hit else (last[1], last[2], last[0])
    outcome = Outcome(
        setup=setup.name,
        policy=policy,
        seed=seed,
        reached=watch.hit is not None,
        emulated_s=clock,
        trajectories_per_agent=trajectories,
        rounds=done,
        final_metric=watch.metric,
        mean_staleness=float(np.mean(watch.staleness)) if watch.staleness else 0.0,
        stale_dropped=watch.stale,
        wall_s=wall,
    )
    return outcome, watch.figures, theta


def measure(setups: list[Setup], seeds: range, repeat: bool) -> list[Outcome]:
    outcomes = []
    for setup in setups:
        first_buffered = f"buffered M={setup.buffers[0]}"
        for policy in policies(setup):
            for seed in seeds:
                outcome, figures, theta = one_run(setup, policy, seed)
                if repeat and policy == first_buffered:
                    again, figures_again, theta_again = one_run(setup, policy, seed)
                    same = (
                        torch.equal(theta, theta_again)
                        and figures == figures_again
                        and dataclasses.replace(again, wall_s=0)
                        == dataclasses.replace(outcome, wall_s=0)
                    )
                    outcome = Outcome(**{**asdict(outcome), "repeat_identical": same})
                outcomes.append(outcome)
                logging.info("%s", outcome)
    return outcomes


def interval(values: list[float]) -> tuple[float, float, float]:
    """Mean and its 95% percentile-bootstrap interval (server/commands/plot_stats.py's
    convention)."""
    array = np.asarray(values, dtype=float)
    if array.size < 2:
        return float(array.mean()), float(array.mean()), float(array.mean())
    low, high = stratified_bootstrap_ci(array[:, None], "mean")
    return float(array.mean()), float(low), float(high)


def summary(outcomes: list[Outcome]) -> list[dict[str, Any]]:
    rows = []
    for setup in dict.fromkeys(o.setup for o in outcomes):
        for policy in dict.fromkeys(o.policy for o in outcomes if o.setup == setup):
            group = [o for o in outcomes if o.setup == setup and o.policy == policy]
            repeats = [o.repeat_identical for o in group if o.repeat_identical is not None]
            rows.append(
                {
                    "setup": setup,
                    "policy": policy,
                    "seeds": len(group),
                    "reached": sum(o.reached for o in group),
                    "emulated_s": interval([o.emulated_s for o in group]),
                    "trajectories_per_agent": interval([o.trajectories_per_agent for o in group]),
                    "rounds": interval([float(o.rounds) for o in group]),
                    "mean_staleness": float(np.mean([o.mean_staleness for o in group])),
                    "repeat_identical": all(repeats) if repeats else None,
                }
            )
    return rows


def _cell(figure: tuple[float, float, float], censored: bool, digits: int) -> str:
    mean, low, high = figure
    prefix = "≥ " if censored else ""
    return f"{prefix}{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| set-up | policy | reached | emulated s to threshold | trajectories/agent "
        "| rounds (versions of θ̃) | mean staleness | repeat bit-identical |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        censored = row["reached"] < row["seeds"]
        repeat = {None: "—", True: "yes", False: "**no**"}[row["repeat_identical"]]
        lines.append(
            f"| {row['setup']} | {row['policy']} | {row['reached']}/{row['seeds']} | "
            f"{_cell(row['emulated_s'], censored, 2)} | "
            f"{_cell(row['trajectories_per_agent'], censored, 0)} | "
            f"{_cell(row['rounds'], censored, 0)} | {row['mean_staleness']:.2f} | {repeat} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Two panels (emulated time, trajectories per agent), one group of bars per set-up."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    setups = list(dict.fromkeys(r["setup"] for r in rows))
    names = (
        "wait_all",
        "deadline",
        "buffered, smaller M",
        "buffered, larger M",
        "wait_all, C = smaller M",
    )
    colours = ("tab:grey", "tab:red", "tab:blue", "tab:green", "tab:purple")
    ticks = []
    for setup in setups:
        sizes = [
            r["policy"].split("=")[1] for r in rows if r["setup"] == setup and "M=" in r["policy"]
        ]
        ticks.append(f"{setup}\nM = {', '.join(sizes)}")
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for axis, key, label in (
        (axes[0], "emulated_s", "emulated seconds to threshold"),
        (axes[1], "trajectories_per_agent", "trajectories per agent to threshold"),
    ):
        labelled: set[str] = set()
        for s, setup in enumerate(setups):
            group = [r for r in rows if r["setup"] == setup]
            for p, row in enumerate(group):
                mean, low, high = row[key]
                x = s + (p - (len(group) - 1) / 2) * 0.17
                axis.bar(
                    x,
                    mean,
                    0.17,
                    color=colours[p],
                    hatch="//" if row["reached"] < row["seeds"] else None,
                    edgecolor="black",
                    label=names[p] if names[p] not in labelled else None,
                )
                labelled.add(names[p])
                axis.errorbar(x, mean, yerr=[[mean - low], [high - mean]], color="black", capsize=3)
        axis.set_xticks(range(len(setups)), ticks, fontsize=8)
        axis.set_yscale("log")
        axis.set_ylabel(label)
    axes[0].legend(fontsize=8)
    figure.suptitle(
        "Round policies in process, counted clock: mean over seeds, 95% bootstrap interval "
        "(hatched: not every seed reached the threshold; those count at the budget's end)",
        fontsize=9,
    )
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--setups", default=",".join(DEFAULT_SETUPS))
    parser.add_argument("--no-repeat", action="store_true")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--figure", type=Path, default=FIGURE)
    parser.add_argument(
        "--from-results", action="store_true", help="table and figure of --results, no runs"
    )
    args = parser.parse_args()
    if args.from_results:
        rows = json.loads(args.results.read_text())["summary"]
        print(table(rows))
        plot(rows, args.figure)
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("fedhpg").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    chosen = [SETUPS[name] for name in args.setups.split(",")]
    outcomes = measure(chosen, range(args.seeds), repeat=not args.no_repeat)
    rows = summary(outcomes)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(
        json.dumps(
            {
                "setups": [asdict(s) for s in chosen],
                "summary": rows,
                "runs": [asdict(o) for o in outcomes],
            },
            indent=1,
        )
    )
    print(table(rows))
    plot(rows, args.figure)
    print(f"\nresults: {args.results}; figure: {args.figure}")
    if (results_file.TABLES / f"{args.results.stem}.json").exists():
        described = (
            "Each round policy on each set-up: how many seeds reach the threshold, the emulated "
            "time and trajectories it takes, and how stale the updates it aggregates are."
        )
        results_file.refresh(
            args.results.stem,
            [results_file.table_from_markdown(table(rows), described)],
            results_file.command_line("benchmarks.async_rounds"),
        )


if __name__ == "__main__":
    main()
