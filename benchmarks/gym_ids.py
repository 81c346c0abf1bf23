"""Three gymnasium ids the project ships no family for, through ``env=gym``: each learns
above the return of a uniformly random policy in the same agents' environments, within the
budget stated (rounds × trajectories per agent and round).

    python -m benchmarks.gym_ids                  # every id, seeds 0 1 2
    python -m benchmarks.gym_ids --only Acrobot-v1 --seeds 0
    python -m benchmarks.gym_ids --table-only

Each run is ``fedhpg-run env=gym env.id=ID <its overrides>`` computed in this process
(``api.run``: the same θ̃ as the agent processes, bit for bit) on the counted virtual clock.
The random policy's return is measured in each agent's own variant (its ``make_env()``, the
run's horizon), over as many episodes as the final evaluation, from fixed seeds. Results go to
``benchmarks/results/gym_ids.json`` as each run ends, their table to
``benchmarks/results/tables/gym_ids.json`` (BENCHMARKS.md); run it at the lowest priority.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import results_file

RESULTS = Path("benchmarks/results/gym_ids.json")
COMMON = ["env=gym", "agents=homogeneous4", "agents.budget.batch_size=[16]", "agents.clock=counted"]
TITLE = "Any gymnasium id (`env=gym`)"
MEASURES = [*results_file.LEARNING_CODE, "conf"]
SETUP = (
    "Three ids the project ships no family for, each `fedhpg-run env=gym env.id=ID` with the "
    "variation below, K = 4 (`agents=homogeneous4`, B = 16, τ = 1, server Adam 0.01, GPOMDP "
    "with mean baseline, 32-32 MLP), in process on the counted clock (the same θ̃ as agent "
    "processes). The learned return is the unified policy's greedy return averaged over the 4 "
    "agents' environments; the random return is a uniformly random policy's in the same "
    "environments, same horizon and episode count. `make test-long` runs seed 0 of each "
    "(`tests/test_gym_family.py`)."
)


@dataclass(frozen=True)
class Case:
    env_id: str
    overrides: tuple[str, ...]
    """What this id needs besides ``COMMON`` (its variation, horizon, step size)."""
    rounds: int
    episodes: int
    """Evaluation episodes per agent, for the learned and the random policy."""


CASES = {
    case.env_id: case
    for case in (
        Case(
            "MountainCar-v0",
            ("env.horizon=500", "+env.vary.force={uniform: {low: 0.001, high: 0.004}}"),
            rounds=40,
            episodes=20,
        ),
        Case(
            "Acrobot-v1",
            ("+env.vary.LINK_MASS_1={spread: 0.4}", "+env.vary.LINK_LENGTH_1={spread: 0.4}"),
            rounds=40,
            episodes=20,
        ),
        Case(
            "FrozenLake-v1",
            (
                "+env.vary.success_rate={uniform: {low: 0.34, high: 0.9}}",
                "strategy.params.step_size=0.1",
            ),
            rounds=60,
            episodes=100,
        ),
    )
}


def overrides_of(case: Case, seed: int) -> list[str]:
    return [
        *COMMON,
        f"env.id={case.env_id}",
        *case.overrides,
        f"rounds={case.rounds}",
        f"eval.every={case.rounds}",
        f"eval.episodes={case.episodes}",
        f"seed={seed}",
    ]


def random_return(run: Any, episodes: int, seed: int) -> float:
    """The mean over agents of a uniformly random policy's return in each agent's variant."""
    from fedhpg.common.heterogeneity.variants import run_variants, training_horizon

    means = []
    for variant in run_variants(run):
        env = variant.make_env()
        env.action_space.seed(seed)
        horizon = training_horizon(run, variant)
        returns = []
        for episode in range(episodes):
            env.reset(seed=seed * 10_000 + episode)
            total = 0.0
            for _ in range(horizon):
                _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
                total += float(reward)
                if terminated or truncated:
                    break
            returns.append(total)
        env.close()
        means.append(float(np.mean(returns)))
    return float(np.mean(means))


def measure(case: Case, seed: int) -> dict[str, Any]:
    from fedhpg.server.commands import api

    overrides = overrides_of(case, seed)
    started = time.perf_counter()
    result = api.run(overrides=overrides)
    seconds = time.perf_counter() - started
    assert result.last_evaluation is not None
    learned = float(np.mean([e.return_mean for e in result.last_evaluation.values()]))
    return {
        "env_id": case.env_id,
        "seed": seed,
        "command": "fedhpg-run " + " ".join(f"'{o}'" if " " in o else o for o in overrides),
        "trajectories_per_agent": result.records[-1]["trajectories_per_agent"],
        "learned_return": learned,
        "random_return": random_return(result.config, case.episodes, seed),
        "seconds": seconds,
    }


def table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| env.id | trajectories per agent | random policy | learned (3 seeds) | above random |"
        " seconds per run |",
        "|---|---|---|---|---|---|",
    ]
    for env_id in CASES:
        runs = [r for r in results if r["env_id"] == env_id]
        if not runs:
            continue
        learned = [r["learned_return"] for r in runs]
        rand = statistics.fmean(r["random_return"] for r in runs)
        above = sum(r["learned_return"] > r["random_return"] for r in runs)
        lines.append(
            f"| `{env_id}` | {runs[0]['trajectories_per_agent']:g} | {rand:.3g} | "
            f"{statistics.fmean(learned):.3g} ({', '.join(f'{v:.3g}' for v in learned)}) | "
            f"{above} of {len(runs)} | {statistics.fmean(r['seconds'] for r in runs):.0f} |"
        )
    return "\n".join(lines)


def summary(runs: list[dict[str, Any]]) -> str:
    """What the table says: whether each id learns above a random policy on every seed."""
    below = sorted({r["env_id"] for r in runs if r["learned_return"] <= r["random_return"]})
    if not below:
        return "Each id learns above a random policy on every seed."
    return (
        "Not every id learns above a random policy on every seed: "
        + ", ".join(f"`{env_id}`" for env_id in below)
        + ' falls short on some ("above random" counts the seeds where it is higher).'
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=sorted(CASES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--table-only", action="store_true")
    args = parser.parse_args()
    stored = json.loads(RESULTS.read_text()) if RESULTS.exists() else {"runs": []}
    if not args.table_only:
        for env_id, case in CASES.items():
            if args.only and env_id != args.only:
                continue
            for seed in args.seeds:
                outcome = measure(case, seed)
                stored["runs"] = [
                    r for r in stored["runs"] if (r["env_id"], r["seed"]) != (env_id, seed)
                ] + [outcome]
                stored["date"] = time.strftime("%Y-%m-%d")
                stored["commit"] = results_file.commit()
                RESULTS.parent.mkdir(parents=True, exist_ok=True)
                RESULTS.write_text(json.dumps(stored, indent=2) + "\n")
                print(
                    f"{env_id} seed {seed}: learned {outcome['learned_return']:.3g}, random "
                    f"{outcome['random_return']:.3g} ({outcome['seconds']:.0f} s)",
                    flush=True,
                )
    print(table(stored["runs"]))
    measured_now = {(env_id, seed) for env_id in CASES for seed in args.seeds}
    if (
        args.only
        or args.table_only
        or any((r["env_id"], r["seed"]) not in measured_now for r in stored["runs"])
    ):
        print(f"{RESULTS} holds earlier runs: the table is not stored as one run's result")
        return
    results_file.write(
        "gym_ids",
        title=TITLE,
        order=20,
        command="python -m benchmarks.gym_ids",
        measures=MEASURES,
        setup=SETUP,
        data=[str(RESULTS)],
        date=stored.get("date"),
        commit_hash=stored.get("commit"),
        tables=[
            results_file.table_from_markdown(
                table(stored["runs"]),
                summary=summary(stored["runs"]),
            )
        ],
    )


if __name__ == "__main__":
    main()
