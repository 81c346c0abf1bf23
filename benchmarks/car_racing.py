"""CarRacing-v3 (96×96×3 image observations, the CNN policy) learning above a uniformly random
policy with K = 4 agents, on a short budget a 2-core machine can pay for.

    python -m benchmarks.car_racing                 # seed 0, 40 rounds (~20 min on 2 cores)
    python -m benchmarks.car_racing --rounds 2      # a smoke run

The run is ``fedhpg-run`` with :data:`OVERRIDES` computed in this process (``api.run``: the
same θ̃ as agent processes) on the counted virtual clock, its run directory under
``runs/car_racing-seed<S>``. Reported: the mean sampled training return of the first and the
last five rounds (the stochastic policy's own episodes), θ̃₀'s and the final θ̃'s greedy
return with the final evaluation's seeds, and a uniformly random policy's return in the same
agents' environments, horizon and episode count (:func:`benchmarks.gym_ids.random_return`).
The result goes to ``benchmarks/results/car_racing.json`` with its command, date, commit and
machine, the figure (``fedhpg-plot``, training return per round) to
``docs/figures/car_racing.png``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks import results_file
from benchmarks.gym_ids import random_return
from benchmarks.presets import initial_return

RESULTS = Path("benchmarks/results/car_racing.json")
FIGURE = Path("docs/figures/car_racing.png")
OVERRIDES = [
    "env=gym",
    "env.id=CarRacing-v3",
    "+env.kwargs.continuous=false",  # Discrete(5): nothing, left, right, gas, brake
    "env.horizon=300",
    "agents=homogeneous4",
    "agents.budget.batch_size=[2]",
    "agents.clock=counted",
    "eval.episodes=2",
]
WINDOW = 5
"""Rounds averaged at each end of the training curve."""
MEASURES = [*results_file.LEARNING_CODE, "conf"]
SETUP = (
    "`{command}`, in process. Training return: the sampled episodes' mean over the 4 agents; "
    "greedy returns over {episodes} episodes per agent; the random policy's in the same "
    "environments, horizon and episode count."
)


def overrides_of(seed: int, rounds: int) -> list[str]:
    every = max(rounds // 4, 1)
    return [*OVERRIDES, f"rounds={rounds}", f"eval.every={every}", f"seed={seed}"]


def measure(seed: int, rounds: int, out_dir: Path) -> dict[str, Any]:
    from fedhpg.server.commands import api

    overrides = overrides_of(seed, rounds)
    started = time.perf_counter()
    result = api.run(overrides=overrides, out_dir=out_dir)
    seconds = time.perf_counter() - started
    assert result.last_evaluation is not None
    training = [
        statistics.fmean(agent["train_return"] for agent in record["agents"])
        for record in result.records
    ]
    episodes = result.config.eval.episodes
    return {
        "command": "fedhpg-run " + " ".join(overrides),
        "date": time.strftime("%Y-%m-%d"),
        "commit": results_file.commit(),
        "machine": results_file.machine(),
        "seed": seed,
        "rounds": rounds,
        "seconds": round(seconds, 1),
        "train_return_first": statistics.fmean(training[:WINDOW]),
        "train_return_last": statistics.fmean(training[-WINDOW:]),
        "train_return": training,
        "initial_greedy_return": initial_return(overrides, rounds),
        "final_greedy_return": statistics.fmean(
            e.return_mean for e in result.last_evaluation.values()
        ),
        "random_return": random_return(result.config, episodes, seed),
        "episodes": episodes,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rounds", type=int, default=40)
    args = parser.parse_args()
    out_dir = Path(f"runs/car_racing-seed{args.seed}")
    outcome = measure(args.seed, args.rounds, out_dir)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(outcome, indent=2) + "\n")
    report(outcome)
    subprocess.run(
        [
            str(Path(sys.executable).parent / "fedhpg-plot"),
            str(out_dir),
            "--metric=train_return",
            "--x=rounds",
            f"--label=seed {args.seed}",
            f"--out={FIGURE}",
            "--title=CarRacing-v3 (discrete), K = 4, CNN policy: sampled training return",
        ],
        check=True,
    )
    print(
        f"training return {outcome['train_return_first']:.1f} (first {WINDOW} rounds) → "
        f"{outcome['train_return_last']:.1f} (last {WINDOW}); greedy θ̃₀ "
        f"{outcome['initial_greedy_return']:.1f} → {outcome['final_greedy_return']:.1f}; "
        f"random policy {outcome['random_return']:.1f}; {outcome['seconds']:.0f} s"
    )


def _verdict(outcome: dict[str, Any]) -> str:
    """Whether the run ends above the random policy, by both returns, from its figures."""
    random = outcome["random_return"]
    ends = {
        "training return": outcome["train_return_last"],
        "greedy return": outcome["final_greedy_return"],
    }
    above = [name for name, value in ends.items() if value > random]
    figures = " and ".join(f"the {name} ends at {value:.1f}" for name, value in ends.items())
    if len(above) == len(ends):
        verdict = "The CNN policy learns above random on image observations"
    elif above:
        verdict = f"Only the {above[0]} ends above random"
    else:
        verdict = "The CNN policy does not end above random on this run"
    return f"{verdict}: {figures}, against the random policy's {random:.1f}."


def report(outcome: dict[str, Any], summary: str | None = None) -> None:
    """The run's table, as a result for BENCHMARKS.md (stamped with the run's own date,
    commit and machine)."""
    rounds = int(outcome["rounds"])
    row = [
        str(outcome["seed"]),
        f"{outcome['random_return']:.1f}",
        f"{outcome['train_return_first']:.1f} → {outcome['train_return_last']:.1f}",
        f"{outcome['initial_greedy_return']:.1f} → {outcome['final_greedy_return']:.1f}",
        f"{outcome['seconds']:,.0f}",
    ]
    last = f"{rounds - WINDOW + 1}–{rounds}"
    results_file.write(
        "car_racing",
        title="Images: `CarRacing-v3` with the CNN policy",
        order=30,
        command="python -m benchmarks.car_racing" + (f" --rounds {rounds}" if rounds != 40 else ""),
        measures=MEASURES,
        setup=SETUP.format(command=outcome["command"], episodes=outcome["episodes"]),
        data=[str(RESULTS)],
        date=outcome["date"],
        commit_hash=outcome["commit"],
        machine_name=outcome["machine"],
        keep_summaries=summary is not None,
        tables=[
            {
                "columns": [
                    "seed",
                    "random policy",
                    f"training return, rounds 1–{WINDOW} → {last}",
                    f"greedy θ̃₀ → θ̃ after round {rounds}",
                    "wall (s)",
                ],
                "rows": [row],
                "summary": summary or _verdict(outcome),
                "figure": {"path": str(FIGURE), "caption": "sampled training return per round"},
            }
        ],
    )


if __name__ == "__main__":
    main()
