"""``make figures``: rerun the paper's three GridWorld experiments (Section VI) over 5 seeds
with ``fedhpg-run -m`` (real processes), then draw them with ``fedhpg-plot`` into
``docs/figures/fig{1,2,3}.png`` and summarise them in ``docs/figures/summary.md``: the mean
over seeds and its 95% percentile-bootstrap CI, as every figure of the project shows.
``--plot-only`` redraws figures and summary from the sweeps already in ``runs/figures/``.
The summary's table is also the result table ``benchmarks/results/tables/figures.json``;
``--tables-only`` writes that again from ``docs/figures/summary.md`` alone, stamped with the
date, commit and machine it was measured with.
"""

from __future__ import annotations

import argparse
import math
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import results_file
from fedhpg.server.commands.plot import find_runs, group_runs
from fedhpg.server.commands.plot import main as plot_main
from fedhpg.server.commands.plot_stats import stratified_bootstrap_ci

BIN = Path(sys.prefix) / "bin"
SEEDS = "0,1,2,3,4"
SWEEPS = Path("runs/figures")
FIGURES = Path("docs/figures")
SUCCESS = 0.9

EXPERIMENTS = {
    "fig1": ("fig1_batch_size", "agents.budget.batch_size=[2],[2,5,10,20],[20]",
             "Fig. 1 — batch sizes B_k (4 GridWorld agents, τ=2)"),
    "fig2": ("fig2_local_iters", "agents.budget.local_iters=[2,2,3,3],[5,5,6,6]",
             "Fig. 2 — local iterations τ_k (4 GridWorld agents, B=5)"),
    "fig3": ("fig3_vr_inner_loops", "agents.budget.inner_steps=[1],[3],[6]",
             "Fig. 3 — FedHPGVR inner loop N (B=10, b=4)"),
}  # fmt: skip


def sweep(name: str, experiment: str, grid: str) -> Path:
    directory = SWEEPS / name
    shutil.rmtree(directory, ignore_errors=True)
    command = [
        str(BIN / "fedhpg-run"), "-m", f"experiment={experiment}", grid, f"seed={SEEDS}",
        f"hydra.sweep.dir={directory}",
    ]  # fmt: skip
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return directory


def _interval(values: list[float], digits: int = 3) -> str:
    """Mean [95% percentile-bootstrap CI over seeds]; the value alone for one seed."""
    mean = statistics.mean(values)
    if len(values) < 2:
        return f"{mean:.{digits}f}"
    low, high = stratified_bootstrap_ci(np.array(values)[:, None], "mean")
    return f"{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def summary(name: str, directory: Path) -> list[str]:
    rows = []
    for label, runs in group_runs(find_runs([directory])).items():
        finals, reach = [], []
        for run in runs:
            evals = [r for r in run.records if "eval" in r]
            tail = evals[-10:]
            finals.append(
                statistics.mean(
                    statistics.mean(e["return_mean"] for e in r["eval"].values()) for r in tail
                )
            )
            hit = next(
                (
                    r["round"]
                    for r in evals
                    if statistics.mean(e["success_rate"] for e in r["eval"].values()) >= SUCCESS
                ),
                None,
            )
            reach.append(float(hit) if hit is not None else float("nan"))
        reached = [r for r in reach if not math.isnan(r)]
        rounds = _interval(reached, digits=1) if reached else "never"
        rows.append(
            f"| {name} | {label} | {_interval(finals)} | {rounds} ({len(reached)}/{len(reach)}) |"
        )
    return rows


def _seeds(cell: str) -> tuple[int, int]:
    """(seeds reaching, seeds) from a reach cell, ``... (k/n)``."""
    reached, _, seeds = cell.rsplit("(", 1)[1].rstrip(")").partition("/")
    return int(reached), int(seeds)


def table_summary(rows: list[list[str]]) -> str:
    """Which settings reach the success threshold on every seed, and the lowest final return."""
    missing = [f"{r[0]} {r[1]} ({'/'.join(map(str, _seeds(r[3])))})" for r in rows
               if _seeds(r[3])[0] < _seeds(r[3])[1]]  # fmt: skip
    seeds = sorted({_seeds(r[3])[1] for r in rows})
    if missing:
        text = f"Not every seed reaches a mean success of {SUCCESS}: {', '.join(missing)}"
    else:
        counts = " or ".join(map(str, seeds))
        text = f"Every setting reaches a mean success of {SUCCESS} on all {counts} seeds"
    lowest = min(rows, key=lambda r: float(r[2].split(" ")[0]))
    return (
        f"{text}; the lowest final greedy return is {lowest[0]}'s {lowest[1]} "
        f"({lowest[2].split(' ')[0]})."
    )


def result_tables(markdown: str) -> list[results_file.Table]:
    """The summary's table, with its summary computed from the rows."""
    found = results_file.table_from_markdown(markdown, "")
    found["summary"] = table_summary(found["rows"])
    return [found]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--plot-only", action="store_true", help=f"redraw from {SWEEPS}")
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help="only the result table from docs/figures/summary.md, stamped with its measurement",
    )
    args = parser.parse_args()
    if args.tables_only:
        results_file.rerender("figures", result_tables((FIGURES / "summary.md").read_text()))
        return
    started = time.monotonic()
    FIGURES.mkdir(parents=True, exist_ok=True)
    lines = [
        "| figure | setting | final greedy return, last 10 evaluations (mean [95% CI]) "
        f"| first round with mean success ≥ {SUCCESS} (mean [95% CI], seeds reaching) |",
        "|---|---|---|---|",
    ]
    for name, (experiment, grid, title) in EXPERIMENTS.items():
        directory = SWEEPS / name if args.plot_only else sweep(name, experiment, grid)
        plot_main([str(directory), "--out", str(FIGURES / f"{name}.png"), "--title", title])
        lines += summary(name, directory)
        sys.stdout.write(f"{name}: done after {time.monotonic() - started:.0f} s\n")
        sys.stdout.flush()
    heterogeneous = [
        run.path for run in find_runs([SWEEPS / "fig1"])
        if run.config["agents"]["budget"]["batch_size"] == [2, 5, 10, 20]
    ]  # fmt: skip
    plot_main(
        [*map(str, heterogeneous), "--per-agent", "--metric", "train_return",
         "--out", str(FIGURES / "fig1_per_agent.png"),
         "--title", "Fig. 1, per agent, B = (2, 5, 10, 20): local training return"]
    )  # fmt: skip
    lines.append(
        "\nCI: 95% percentile bootstrap over the 5 seeds (2,000 resamples; "
        "fedhpg.server.commands.plot_stats), the band drawn in every figure."
    )
    (FIGURES / "summary.md").write_text("\n".join(lines) + "\n")
    if not args.plot_only:  # a redraw keeps the stamps of the sweeps it reads
        command = results_file.command_line("benchmarks.figures")
        results_file.refresh("figures", result_tables("\n".join(lines)), command)
    sys.stdout.write("\n".join(lines) + f"\n\nall figures in {time.monotonic() - started:.0f} s\n")


if __name__ == "__main__":
    main()
