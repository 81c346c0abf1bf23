"""Trajectories per agent until the unified policy solves every agent's GridWorld (greedy
success ≥ 0.9 in all four environments), FedHPG against FedHPGVR, median over 5 seeds.

Runs the in-process runner, which the distributed runtime reproduces bit for bit.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import torch

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


if __name__ == "__main__":
    print(table(run()))
