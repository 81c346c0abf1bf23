"""Trajectories per agent until the unified policy solves every agent's GridWorld (greedy
success ≥ 0.9 in all four environments), FedHPG against FedHPGVR, median over 5 seeds.

Runs the in-process runner, which the distributed runtime reproduces bit for bit.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import torch

from benchmarks import results_file
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

THRESHOLD = 0.9
SEEDS = (0, 1, 2, 3, 4)
MAX_ROUNDS = 100


@dataclass(frozen=True)
class ThresholdResult:
    algo: str
    seed: int
    rounds: int | None
    trajectories_per_agent: float | None
    wall_s: float


def time_to_threshold(algo: str, seed: int) -> ThresholdResult:
    run = compose([f"algo.name={algo}", f"seed={seed}", f"rounds={MAX_ROUNDS}", "eval.every=1"])
    hit: list[tuple[int, float]] = []

    def watch(record: RoundRecord, _: torch.Tensor) -> None:
        solved = record.eval and min(e.success_rate for e in record.eval.values()) >= THRESHOLD
        if solved and not hit:
            hit.append((record.round, record.trajectories_per_agent))

    started = time.perf_counter()
    run_in_process(run, on_round=[watch])
    wall = time.perf_counter() - started
    if not hit:
        return ThresholdResult(algo, seed, None, None, wall)
    return ThresholdResult(algo, seed, hit[0][0], hit[0][1], wall)


def run() -> list[ThresholdResult]:
    torch.set_num_threads(1)
    return [time_to_threshold(algo, seed) for algo in ("fedhpg", "fedhpgvr") for seed in SEEDS]


def table(results: list[ThresholdResult]) -> str:
    lines = [
        "| algorithm | trajectories per agent to threshold (median) | per seed "
        "| rounds (median) | wall per 100-round run (s) |",
        "|---|---|---|---|---|",
    ]
    for algo in ("fedhpg", "fedhpgvr"):
        rows = [r for r in results if r.algo == algo]
        reached = [r.trajectories_per_agent for r in rows if r.trajectories_per_agent is not None]
        rounds = [r.rounds for r in rows if r.rounds is not None]
        per_seed = ", ".join(
            "—" if r.trajectories_per_agent is None else f"{r.trajectories_per_agent:.0f}"
            for r in rows
        )
        median = (
            f"{statistics.median(reached):.0f}" if len(reached) == len(rows) else "not all seeds"
        )
        lines.append(
            f"| {algo} | {median} | {per_seed} | "
            f"{statistics.median(rounds) if rounds else '—'} | "
            f"{statistics.median(r.wall_s for r in rows):.1f} |"
        )
    return "\n".join(lines)


NAMES = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR"}


def summary(results: list[ThresholdResult]) -> str:
    """What the table says, from the runs: whether every seed reaches the threshold, and which
    algorithm needs fewer trajectories per agent and fewer rounds at the median."""
    missed = [NAMES[a] for a in NAMES if any(r.rounds is None for r in results if r.algo == a)]
    if missed:
        who = " and ".join(missed)
        return f"{who} did not reach the threshold on every seed in {MAX_ROUNDS} rounds."

    def median(algo: str, field: str) -> float:
        return float(statistics.median(getattr(r, field) for r in results if r.algo == algo))

    def fewer(field: str, what: str) -> str:
        ours, theirs = median("fedhpg", field), median("fedhpgvr", field)
        if ours == theirs:
            return f"both need {ours:,.0f} {what} at the median"
        first, second = ("FedHPG", "FedHPGVR") if ours < theirs else ("FedHPGVR", "FedHPG")
        low, high = sorted((ours, theirs))
        return (
            f"{first} needs fewer {what} than {second} at the median "
            f"({low:,.0f} against {high:,.0f})"
        )

    spread = [r.trajectories_per_agent or 0.0 for r in results]
    trajectories = fewer("trajectories_per_agent", "trajectories per agent")
    return (
        f"Both solve all four environments on every seed; {trajectories}, and "
        f"{fewer('rounds', 'rounds')}. The seeds spread widely ({min(spread):,.0f}–"
        f"{max(spread):,.0f} trajectories per agent)."
    )


def main() -> None:
    results = run()
    print(table(results))
    results_file.write(
        "gridworld_threshold",
        title="GridWorld: trajectories until every environment is solved",
        order=100,
        command="python -m benchmarks.gridworld_threshold",
        measures=[*results_file.LEARNING_CODE, *results_file.RUNTIME_CODE],
        setup=(
            "The demo federation (4 heterogeneous GridWorlds, B = 8/12/16/20, τ = 2/2/3/3 for "
            "FedHPG; N = 3, b_k = 5 for FedHPGVR; η = 0.5), in process (which the distributed "
            "runtime reproduces bit for bit), greedy evaluation after every round; trajectories "
            "per agent when success ≥ 0.9 in all four environments first holds, 5 seeds."
        ),
        tables=[results_file.table_from_markdown(table(results), summary(results))],
    )


if __name__ == "__main__":
    main()
