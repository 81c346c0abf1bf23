"""Is the device-resident path the same experiment? CartPole, K = 1,000 agents of the shipped
population, learnt through the torch CartPole (``algo.envs=auto``) and through gymnasium's own
CartPole (``algo.envs=gymnasium``), everything else equal: the torch engine on the CPU, the
``env=cartpole`` preset (FedPG-BR's arrangement, server Adam), the population's budgets, so the
two paths sample the same trajectories per agent in every round.

Every ``--every`` rounds θ̃ is evaluated greedily in each of the 1,000 agents' environments
(one episode each: 1,000 episodes); per path, the mean over agents for each of ``--seeds``
seeds. The two paths' float rounding differs (float32 against gymnasium's float64), so their
runs part after a few steps and only their distributions can agree: the table gives each
path's mean and spread over seeds at each evaluation, and the difference of the means against
the seeds' spread.

    nice -n 19 python -m benchmarks.device_learning            # 5 seeds, 15 rounds
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from benchmarks import results_file
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

RESULTS = Path(__file__).parent / "results" / "device_learning.json"
PATHS = ("auto", "gymnasium")


def curve(path: str, seed: int, agents: int, rounds: int, every: int) -> dict[str, list[float]]:
    """(trajectories per agent, mean greedy return over agents) at each evaluation of one run."""
    run = compose([
        "env=cartpole", "agents=population", f"agents.num_agents={agents}",
        "algo.engine=torch", f"algo.envs={path}", f"seed={seed}", f"rounds={rounds}",
        f"eval.every={every}", "eval.episodes=1",
    ])  # fmt: skip
    points: dict[str, list[float]] = {"round": [], "trajectories": [], "greedy_return": []}

    def record(entry: RoundRecord, _: torch.Tensor) -> None:
        if entry.eval is not None:
            points["round"].append(entry.round)
            points["trajectories"].append(entry.trajectories_per_agent)
            points["greedy_return"].append(
                statistics.mean(e.return_mean for e in entry.eval.values())
            )

    started = time.perf_counter()
    run_in_process(run, on_round=[record])
    points["wall_s"] = [time.perf_counter() - started]
    return points


def summary(results: dict[str, dict[int, dict[str, list[float]]]]) -> list[dict[str, float]]:
    """Per evaluation: each path's mean and sd over seeds, and the difference of the means in
    units of the seeds' pooled sd."""
    first = next(iter(results["auto"].values()))
    rows = []
    for i, round_number in enumerate(first["round"]):
        row: dict[str, float] = {"round": round_number, "trajectories": first["trajectories"][i]}
        for path in PATHS:
            values = [points["greedy_return"][i] for points in results[path].values()]
            row[f"{path}_mean"] = statistics.mean(values)
            row[f"{path}_sd"] = statistics.stdev(values) if len(values) > 1 else math.nan
        pooled = math.sqrt((row["auto_sd"] ** 2 + row["gymnasium_sd"] ** 2) / 2)
        row["difference"] = row["auto_mean"] - row["gymnasium_mean"]
        row["difference_in_sd"] = row["difference"] / pooled if pooled > 0 else math.nan
        rows.append(row)
    return rows


def described(rows: list[dict[str, float]]) -> str:
    """How far apart the two paths' means come, in units of the seeds' pooled sd."""
    widest = max(rows, key=lambda r: abs(r["difference_in_sd"]))
    last = rows[-1]
    ahead = "device-resident" if last["difference"] > 0 else "gymnasium"
    return (
        f"The two paths' means differ by at most {abs(widest['difference_in_sd']):.2f} of the "
        f"seeds' pooled sd (round {widest['round']:.0f}); after the last round the "
        f"{ahead} path's mean is ahead by {abs(last['difference']):.1f}, "
        f"{abs(last['difference_in_sd']):.2f} of the pooled sd."
    )


def table(rows: list[dict[str, float]], seeds: int) -> str:
    lines = [
        f"| round | trajectories per agent | device-resident: mean ± sd ({seeds} seeds) "
        "| gymnasium: mean ± sd | difference | difference ÷ pooled sd |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['round']:.0f} | {r['trajectories']:.1f} "
            f"| {r['auto_mean']:.1f} ± {r['auto_sd']:.1f} "
            f"| {r['gymnasium_mean']:.1f} ± {r['gymnasium_sd']:.1f} "
            f"| {r['difference']:+.1f} | {r['difference_in_sd']:+.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--every", type=int, default=5)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results: dict[str, dict[int, dict[str, list[float]]]] = {path: {} for path in PATHS}
    for seed in range(args.seeds):
        for path in PATHS:  # interleaved: load on the machine falls on both alike
            results[path][seed] = curve(path, seed, args.agents, args.rounds, args.every)
            final = results[path][seed]["greedy_return"][-1]
            wall = results[path][seed]["wall_s"][0]
            print(f"seed {seed}, {path}: final greedy return {final:.1f} ({wall:.0f} s)",
                  flush=True)  # fmt: skip
    rows = summary(results)
    print(table(rows, args.seeds))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "agents": args.agents, "rounds": args.rounds, "seeds": args.seeds,
        "runs": {path: {str(s): p for s, p in runs.items()} for path, runs in results.items()},
        "summary": rows,
    }, indent=1) + "\n")  # fmt: skip
    print(f"wrote {args.out}")
    if args.out == RESULTS:
        results_file.refresh(
            "device_learning",
            [results_file.table_from_markdown(table(rows, args.seeds), described(rows))],
            results_file.command_line("benchmarks.device_learning"),
        )


if __name__ == "__main__":
    main()
