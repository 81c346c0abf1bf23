"""LunarLander-v3 and HalfCheetah-v5, K=10, 10,000 trajectories per agent, through the
distributed runtime (``fedhpg-run``: a server and ten agent processes), next to FedPG-BR's
published returns. Homogeneous variants (``env.level=0``), greedy evaluation.

    python -m benchmarks.learning_long --task lunarlander --seeds 0 1 2 3 4
    python -m benchmarks.learning_long --task halfcheetah --seeds 0 1 2
    python -m benchmarks.learning_long --task lunarlander --plot-only

Each finished seed is stored in ``benchmarks/results/<task>.json`` (the whole curve, wall
times, memory, the exact overrides), so an interrupted sweep keeps what it has and the table
and figure (``docs/figures/<task>_learning.png``) are rebuilt from that file, and so is the
result table of both tasks, ``benchmarks/results/tables/learning_long.json`` (``--tables-only``:
that table alone from the stored files, stamped with the date, commit and machine they were
measured with). ``--set k=v``
adds Hydra overrides (pilot runs); ``--results`` writes elsewhere. Every run takes 15–60 min
on the project's 2-core machine: run it under ``nice``, one at a time.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from benchmarks import results_file
from benchmarks.runtime import _federation

RESULTS = Path("benchmarks/results")
FIGURES = Path("docs/figures")


@dataclass(frozen=True)
class Task:
    name: str
    title: str
    batch_size: int
    overrides: list[str]
    anchor: tuple[float, float]
    """FedPG-BR's published return after 10^4 trajectories per agent (low, high)."""
    eval_every: int
    horizons: tuple[int, int]
    """(training, evaluation) episode step limits, for the figure's labels."""


# Shared by both tasks: FedPG-BR's arrangement (K=10, τ=1, agents send one plain GPOMDP step
# of size 1, the server applies Adam to the average), greedy evaluation over 10 episodes in
# all (one per agent; the ten environments are identical at level 0).
COMMON = [
    "agents=homogeneous10",
    "agents.budget.local_iters=[1]",
    "env.level=0",
    "algo.name=fedhpg",
    "algo.estimator=gpomdp",
    "algo.baseline=mean",
    "algo.optimizer=sgd",
    "algo.step_size=1.0",
    "strategy=fedadam",
    "eval.episodes=1",
    "eval.greedy=true",
]

TASKS = {
    "lunarlander": Task(
        name="lunarlander",
        title="LunarLander-v3, K=10",
        batch_size=32,
        overrides=[
            "env.family=lunarlander",
            # FedPG-BR: γ=0.99 and Adam 1e-3; γ = 1: docs/environments.md says why.
            "env.gamma=1.0",
            "env.horizon=1000",
            "eval.horizon=1000",
            "agents.budget.batch_size=[32]",
            "policy.hidden=[64,64]",
            "strategy.params.step_size=0.003",
        ],
        anchor=(200.0, 200.0),
        eval_every=4,
        horizons=(1000, 1000),
    ),
    "halfcheetah": Task(
        name="halfcheetah",
        title="HalfCheetah-v5, K=10",
        batch_size=48,
        overrides=[
            "env.family=halfcheetah",
            # FedPG-BR: γ=0.995 and Adam 8e-5; γ = 1: docs/environments.md says why.
            "env.gamma=1.0",
            "env.horizon=500",
            "eval.horizon=1000",
            "agents.budget.batch_size=[48]",
            "policy.hidden=[64,64]",
            "strategy.params.step_size=0.003",
        ],
        anchor=(2500.0, 2700.0),
        eval_every=4,
        horizons=(500, 1000),
    ),
}


@dataclass
class SeedResult:
    task: str
    seed: int
    overrides: list[str]
    trajectories: list[float]
    """Trajectories per agent at each evaluation."""
    returns: list[float]
    """Greedy return at each evaluation, mean over the K agents' episodes."""
    return_stds: list[float]
    env_steps: int
    wall_s: float
    """Launch to exit of ``fedhpg-run``, start-up and evaluations included."""
    train_wall_s: float
    """The server's clock at the last round (from round 1 on)."""
    peak_pss_mib: float
    extra: dict = field(default_factory=dict)

    @property
    def final(self) -> float:
        return self.returns[-1]

    @property
    def best(self) -> float:
        return max(self.returns)


def run_seed(
    task: Task,
    seed: int,
    trajectories: int,
    extra: list[str],
    eval_every: int | None = None,
    keep: Path | None = None,
) -> SeedResult:
    rounds = math.ceil(trajectories / task.batch_size)
    overrides = [
        *COMMON,
        *task.overrides,
        *extra,
        f"seed={seed}",
        f"rounds={rounds}",
        f"eval.every={eval_every or task.eval_every}",
    ]
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        records, _, peak = _federation(overrides, Path(tmp), sample_memory=True, poll_s=1.0)
        wall = time.monotonic() - started
        if keep is not None:  # the run directory (metrics, last checkpoints), for diagnosis
            shutil.copytree(tmp, keep / f"{task.name}-seed{seed}", dirs_exist_ok=True)
    per_agent, steps, cpu = 0.0, 0, 0.0
    xs, ys, stds, train, train_x = [], [], [], [], []
    for record in records:
        agents = record["agents"]
        per_agent += sum(a["trajectories"] for a in agents) / len(agents)
        steps += sum(a["env_steps"] for a in agents)
        cpu += sum(a["compute_s"] for a in agents)
        # The sampling policy's own return: this round's K·B training episodes (stochastic).
        train.append(statistics.mean(a["train_return"] for a in agents))
        train_x.append(per_agent)
        if "eval" in record:
            evals = list(record["eval"].values())
            xs.append(per_agent)
            ys.append(statistics.mean(e["return_mean"] for e in evals))
            # Pooled std over all K·episodes (one episode per agent: the std across agents).
            episodes = [e["return_mean"] for e in evals]
            stds.append(statistics.pstdev(episodes) if len(episodes) > 1 else 0.0)
    return SeedResult(
        task=task.name,
        seed=seed,
        overrides=overrides,
        trajectories=xs,
        returns=ys,
        return_stds=stds,
        env_steps=steps,
        wall_s=wall,
        train_wall_s=records[-1]["wall_time_s"],
        peak_pss_mib=peak / 2**20,
        # Thread CPU time of the local updates, all agents: unlike the wall time, it does not
        # depend on what else the shared machine runs.
        extra={"train_returns": train, "train_trajectories": train_x, "agent_cpu_s": cpu},
    )


def load(path: Path) -> dict[int, SeedResult]:
    if not path.exists():
        return {}
    return {int(k): SeedResult(**v) for k, v in json.loads(path.read_text()).items()}


def save(path: Path, results: dict[int, SeedResult]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {str(k): asdict(v) for k, v in sorted(results.items())}
    partial = path.with_suffix(".json.partial")
    partial.write_text(json.dumps(data, indent=1) + "\n")
    partial.replace(path)


def table(task: Task, results: list[SeedResult]) -> str:
    low, high = task.anchor
    anchor = f"≈{low:,.0f}" if low == high else f"≈{low:,.0f}–{high:,.0f}"
    lines = [
        "| seed | trajectories per agent | greedy return at the end (10 episodes) "
        "| best greedy evaluation | mean of the last 5 greedy evaluations "
        "| stochastic return, last round (K·B episodes) | env steps (all agents) "
        "| wall (min) | agents' CPU (min) | peak PSS (MiB) | FedPG-BR |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        last5 = statistics.mean(r.returns[-5:])
        cpu = r.extra.get("agent_cpu_s")
        cpu_min = f"{cpu / 60:.1f}" if cpu is not None else "—"
        lines.append(
            f"| {r.seed} | {r.trajectories[-1]:,.0f} | {r.final:,.1f} | {r.best:,.1f} | "
            f"{last5:,.1f} | {r.extra['train_returns'][-1]:,.1f} | "
            f"{r.env_steps / 1e6:,.1f} M | {r.wall_s / 60:.1f} | {cpu_min} | "
            f"{r.peak_pss_mib:.0f} | {anchor} |"
        )
    if len(results) > 1:
        finals = [r.final for r in results]
        stochastic = [r.extra["train_returns"][-1] for r in results]
        lines.append(
            f"| **median** | | **{statistics.median(finals):,.1f}** "
            f"({min(finals):,.1f} to {max(finals):,.1f}) | | | "
            f"**{statistics.median(stochastic):,.1f}** "
            f"({min(stochastic):,.1f} to {max(stochastic):,.1f}) | | | | | |"
        )
    return "\n".join(lines)


def _median_range(values: list[float]) -> tuple[str, str]:
    return f"{statistics.median(values):,.1f}", f"({min(values):,.1f}–{max(values):,.1f})"


def _anchor(task: Task) -> str:
    low, high = task.anchor
    return f"≈ {low:,.0f}" if low == high else f"≈ {low:,.0f}–{high:,.0f}"


def stored(folder: Path = RESULTS) -> dict[str, list[SeedResult]]:
    """Each task's stored seeds (``<folder>/<task>.json``), in seed order; tasks with none left
    out."""
    found = {name: load(folder / f"{name}.json") for name in TASKS}
    return {name: [r[s] for s in sorted(r)] for name, r in found.items() if r}


def result_table(results: dict[str, list[SeedResult]]) -> str:
    """Both tasks side by side: the greedy return at the end and the stochastic return of the
    last round, median (range) over the seeds, beside FedPG-BR's published return; the
    training episodes' length named where it is not the evaluation's."""
    lines = [
        "| task | greedy return at the end, median (range) "
        "| stochastic return of the last round, median (range) | FedPG-BR's published |",
        "|---|---|---|---|",
    ]
    for name, runs in results.items():
        task = TASKS[name]
        greedy, greedy_range = _median_range([r.final for r in runs])
        stochastic = " ".join(_median_range([r.extra["train_returns"][-1] for r in runs]))
        training, evaluation = task.horizons
        if training != evaluation:
            stochastic += f" ({training}-step episodes)"
        lines.append(
            f"| {task.title.split(',')[0]} | **{greedy}** {greedy_range} | {stochastic} "
            f"| {_anchor(task)} |"
        )
    return "\n".join(lines)


def summary(results: dict[str, list[SeedResult]]) -> str:
    """Which tasks end above FedPG-BR's published return (the top of its range) on every seed,
    on some, or on none."""
    groups: dict[str, list[str]] = {"every": [], "some": [], "none": []}
    for name, runs in results.items():
        above = [r.final > TASKS[name].anchor[1] for r in runs]
        where = "every" if all(above) else "some" if any(above) else "none"
        groups[where].append(TASKS[name].title.split(",")[0])
    parts = []
    if groups["every"]:
        both = len(groups["every"]) == len(TASKS)
        who = "Both tasks" if both else " and ".join(groups["every"])
        parts.append(f"{who} end above FedPG-BR's published returns on every seed")
    if groups["some"]:
        parts.append(f"{' and '.join(groups['some'])} on some seeds")
    if groups["none"]:
        parts.append(f"{' and '.join(groups['none'])} on no seed")
    return "; ".join(parts) + "." if parts else "No run stored."


def result_tables(results: dict[str, list[SeedResult]]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(result_table(results), summary(results))]


def plot(task: Task, results: list[SeedResult], path: Path) -> None:
    """Greedy and stochastic return: the mean over seeds and its 95% percentile-bootstrap
    band (the project's one convention, :mod:`fedhpg.server.commands.plot`), FedPG-BR's return."""
    import numpy as np

    from fedhpg.server.commands.plot import draw_band, figure_and_axis, legend, save

    figure, axis = figure_and_axis()
    curves = (
        (
            f"greedy, 10 episodes ≤ {task.horizons[1]} steps",
            "tab:blue",
            lambda r: (r.trajectories, r.returns),
        ),
        (
            f"stochastic, training batch ≤ {task.horizons[0]} steps",
            "tab:orange",
            lambda r: (r.extra["train_trajectories"], r.extra["train_returns"]),
        ),
    )
    for label, colour, curve in curves:
        seeds = [
            (np.asarray(x, dtype=float), np.asarray(y, dtype=float)) for x, y in map(curve, results)
        ]
        draw_band(axis, label, seeds, color=colour)
    low, high = task.anchor
    if low == high:
        axis.axhline(low, color="grey", linestyle="--", linewidth=1, label=f"FedPG-BR ≈{low:g}")
    else:
        axis.axhspan(low, high, color="grey", alpha=0.25, label=f"FedPG-BR ≈{low:g}–{high:g}")
    axis.set_xlabel("trajectories per agent")
    axis.set_ylabel("undiscounted episode return")
    axis.set_title(f"{task.title} (fedhpg-run, server Adam)")
    # Room above the curves for the legend: both tasks rise from the lower left.
    bottom, top = axis.get_ylim()
    axis.set_ylim(bottom, top + 0.35 * (top - bottom))
    legend(axis, "mean", loc="upper left")
    path.parent.mkdir(parents=True, exist_ok=True)
    save(figure, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", choices=sorted(TASKS))
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    parser.add_argument("--trajectories", type=int, default=10_000)
    parser.add_argument("--eval-every", type=int, default=None)
    parser.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--results", type=Path, default=None)
    parser.add_argument("--figure", type=Path, default=None)
    parser.add_argument("--plot-only", action="store_true")
    parser.add_argument("--keep-runs", type=Path, default=None, help="copy run directories here")
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help="only the result table from the stored runs, stamped with their measurement",
    )
    args = parser.parse_args()
    if args.tables_only:
        print(result_table(stored()))
        results_file.rerender("learning_long", result_tables(stored()))
        return
    if args.task is None:
        parser.error("--task is required (but with --tables-only)")
    task = TASKS[args.task]
    path = args.results or RESULTS / f"{task.name}.json"
    results = load(path)
    if not args.plot_only:
        for seed in args.seeds:
            result = run_seed(
                task, seed, args.trajectories, args.extra, args.eval_every, args.keep_runs
            )
            results[seed] = result
            save(path, results)
            print(
                f"{task.name} seed {seed}: return {result.final:.1f} (best {result.best:.1f}) "
                f"after {result.trajectories[-1]:.0f} trajectories per agent, "
                f"{result.wall_s / 60:.1f} min",
                flush=True,
            )
    ordered = [results[s] for s in sorted(results)]
    print(table(task, ordered))
    figure = args.figure or FIGURES / f"{task.name}_learning.png"
    plot(task, ordered, figure)
    if args.results is None and not args.extra and not args.plot_only:  # the benchmark's set-up
        results_file.refresh(
            "learning_long",
            result_tables(stored()),
            results_file.command_line("benchmarks.learning_long"),
        )
    print(f"\nresults: {path}; figure: {figure}")


if __name__ == "__main__":
    main()
