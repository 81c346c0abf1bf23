"""Heterogeneous GridWorld with K = 1,000 agents, C = 100 per round (``make bench-scale``).

A real ``fedhpg-run`` federation on two agent hosts; B_k, τ_k and device speeds from the
shipped population; the counted clock. The unified policy is evaluated greedily in all 1,000
agents' environments every few rounds; the figure shows the share of environments it solves
(success ≥ 0.9) and the mean success against emulated device time and trajectories per agent.

    python -m benchmarks.scale_gridworld
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import results_file
from benchmarks.runtime import _federation

RESULTS = Path(__file__).parent / "results" / "scale_gridworld.json"
FIGURE = Path(__file__).parents[1] / "docs" / "scale_gridworld.png"
THRESHOLD = 0.9
AGENTS, PER_ROUND, ROUNDS, EVERY = 1000, 100, 30, 3


def run() -> dict:
    overrides = [
        "env=gridworld",
        "agents=population",
        f"agents.num_agents={AGENTS}",
        f"agents.per_host={AGENTS // 2}",
        "agents.clock=counted",
        "strategy.participation.mode=uniform",
        f"strategy.participation.per_round={PER_ROUND}",
        f"rounds={ROUNDS}",
        f"eval.every={EVERY}",
        "eval.episodes=10",
        "server.register_timeout_s=600",
    ]
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        records, first_round_s, _ = _federation(overrides, Path(tmp), poll_s=0.2)
    emulated = trajectories = 0.0
    curve = []
    for record in records:
        emulated += max((a["emulated_s"] for a in record["agents"]), default=0.0)
        trajectories = record["trajectories_per_agent"]
        if "eval" in record:
            success = np.array([e["success_rate"] for e in record["eval"].values()])
            curve.append(
                {
                    "round": record["round"],
                    "emulated_s": emulated,
                    "trajectories_per_agent": trajectories,
                    "solved_share": float((success >= THRESHOLD).mean()),
                    "mean_success": float(success.mean()),
                    "environments": int(success.size),
                }
            )
    return {
        "overrides": overrides,
        "wall_s": time.monotonic() - started,
        "start_to_round_1_s": first_round_s,
        "curve": curve,
    }


def figure(result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curve = result["curve"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for axis, key, label in (
        (axes[0], "emulated_s", "emulated device time (s)"),
        (axes[1], "trajectories_per_agent", "trajectories per agent (all 1,000)"),
    ):
        x = [point[key] for point in curve]
        axis.plot(x, [p["solved_share"] for p in curve], marker="o", label="share solved (≥ 0.9)")
        axis.plot(x, [p["mean_success"] for p in curve], marker=".", label="mean greedy success")
        axis.axhline(0.95, color="k", linestyle="--", linewidth=0.8, label="95 % of environments")
        axis.set_xlabel(label)
    axes[0].set_ylabel("over the 1,000 agents' environments")
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(f"GridWorld, K = {AGENTS:,}, C = {PER_ROUND} per round, 2 agent hosts")
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=120)


def table(result: dict) -> str:
    """Every evaluation of the run, the first with every environment solved in bold."""
    curve = result["curve"]
    first = next((p["round"] for p in curve if p["solved_share"] >= 1.0), None)
    lines = [
        "| round | emulated s | trajectories per agent "
        f"| environments solved (success ≥ {THRESHOLD}) | mean greedy success |",
        "|---|---|---|---|---|",
    ]
    for p in curve:
        solved = f"{p['solved_share']:.3f}"
        if p["round"] == first:
            solved = f"**{solved}**"
        lines.append(
            f"| {p['round']} | {p['emulated_s']:.2f} | {p['trajectories_per_agent']:.1f} "
            f"| {solved} | {p['mean_success']:.3f} |"
        )
    return "\n".join(lines)


def summary(result: dict) -> str:
    curve = result["curve"]
    solved = next((p for p in curve if p["solved_share"] >= 1.0), None)
    if solved is not None:
        return (
            f"All {AGENTS:,} environments are solved by round {solved['round']}, at "
            f"{solved['trajectories_per_agent']:.1f} trajectories per agent."
        )
    best = max(curve, key=lambda p: p["solved_share"])
    return (
        f"At most {best['solved_share']:.1%} of the {AGENTS:,} environments are solved at once "
        f"(round {best['round']}), never all of them in {ROUNDS} rounds."
    )


def main() -> None:
    result = run()
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=1) + "\n")
    figure(result)
    results_file.write(
        "scale_gridworld",
        title="GridWorld, K = 1,000 on agent hosts",
        order=161,
        command="python -m benchmarks.scale_gridworld",
        measures=[*results_file.RUNTIME_CODE, *results_file.LEARNING_CODE],
        setup=(
            f"Two hosts of {AGENTS // 2}, {PER_ROUND} agents a round, the population's budgets "
            f"and speeds, counted clock, greedy evaluation in all {AGENTS:,} environments every "
            f"{EVERY} rounds."
        ),
        data=["benchmarks/results/scale_gridworld.json"],
        tables=[
            results_file.table_from_markdown(
                table(result),
                summary(result),
                figure={
                    "path": "docs/scale_gridworld.png",
                    "caption": "environments solved against rounds",
                },
            )
        ],
    )
    print(table(result))
    print(summary(result))


if __name__ == "__main__":
    main()
