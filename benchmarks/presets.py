"""One learning result per shipped env group: ``fedhpg-run env=NAME`` with the preset and
nothing else but the run's length, seed and evaluation schedule (a server and four agent
processes on loopback, the default devices), next to a single-agent baseline (K=1, the same
preset, B=14: the default devices' mean batch, so both count the same trajectories per agent)
and gymnasium's documented reward threshold where the task has one.

    python -m benchmarks.presets                       # every family, its default seeds
    python -m benchmarks.presets --only pendulum --seeds 0 1 2
    python -m benchmarks.presets --tables-only          # the table again from the stored runs

Each finished run is stored at once in ``benchmarks/results/presets.json`` (the curve, the
exact overrides, wall time), so an interrupted sweep keeps what it has; the table is rebuilt
from that file and written to ``benchmarks/results/tables/presets.json`` (``--tables-only``:
from the stored runs alone, stamped with the date, commit and machine they were measured with).
The initial greedy return is θ̃₀'s, evaluated in-process with the final evaluation's seeds (an
evaluation depends only on θ̃, seed, agent and round), so initial and final differ by learning
alone. Run it under ``nice`` on a shared machine, one at a time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks import results_file
from benchmarks.runtime import BIN

RESULTS = Path("benchmarks/results/presets.json")

SINGLE_AGENT = [
    "agents.num_agents=1",
    "agents.budget.batch_size=[14]",
    "agents.speeds=[1]",
    "agents.step_delays_s=[0]",
]


@dataclass(frozen=True)
class Plan:
    name: str
    rounds: int
    eval_every: int
    episodes: int
    """Greedy evaluation episodes per agent."""
    seeds: tuple[int, ...]
    threshold: float | None
    """gymnasium's ``reward_threshold`` for the task (None where it documents none)."""
    single_agent: bool = True


PLANS = {
    p.name: p
    for p in (
        Plan("gridworld", 60, 5, 50, (0, 1, 2), None, single_agent=False),
        Plan("cartpole", 40, 5, 10, (0, 1, 2), 475.0),
        Plan("acrobot", 40, 5, 10, (0, 1), -100.0),
        Plan("pendulum", 200, 20, 10, (0, 1), None),
        Plan("lunarlander", 150, 15, 10, (0, 1), 200.0, single_agent=False),
        Plan("lunarlander-continuous", 150, 15, 10, (0, 1), 200.0, single_agent=False),
        Plan("halfcheetah", 200, 20, 5, (0, 1), 4800.0, single_agent=False),
    )
}


@dataclass
class RunResult:
    name: str
    kind: str
    """'federation' (the preset's K=4 devices) or 'single' (K=1)."""
    seed: int
    overrides: list[str]
    trajectories: list[float]
    """Trajectories per agent at each evaluation."""
    returns: list[float]
    """Greedy return at each evaluation, mean over the agents' environments."""
    initial: float
    """θ̃₀'s greedy return with the final evaluation's seeds."""
    wall_s: float
    """Launch to exit of fedhpg-run (less the grace period when it hung at exit)."""
    hung_at_exit: bool = False
    """The server did not exit after its last round and was stopped (see ``federation``)."""


def overrides_for(plan: Plan, seed: int, kind: str) -> list[str]:
    extra = SINGLE_AGENT if kind == "single" else []
    return [
        f"env={plan.name}",
        *extra,
        f"seed={seed}",
        f"rounds={plan.rounds}",
        f"eval.every={plan.eval_every}",
        f"eval.episodes={plan.episodes}",
    ]


def initial_return(overrides: list[str], round_index: int) -> float:
    from fedhpg.common.heterogeneity.variants import run_variants
    from fedhpg.common.learning.worker import initial_theta
    from fedhpg.common.runtime.cli import compose
    from fedhpg.server.pools.inprocess import make_in_process_pool

    run = compose(overrides)
    variants = run_variants(run)
    pool = make_in_process_pool(run, variants)
    try:
        evaluations = pool.evaluate(round_index, initial_theta(variants[0], run), run.eval.episodes)
    finally:
        pool.close()
    return statistics.mean(e.return_mean for e in evaluations.values())


EXIT_GRACE_S = 60.0
"""How long the launcher may take to exit after the last round's metrics line."""


def federation(overrides: list[str], out_dir: Path, rounds: int) -> tuple[list[dict], bool]:
    """Run fedhpg-run; returns (metrics records, whether it hung after its last round).

    A server can hang at exit in ``ConnectionGuard.stop`` (``socket.disable_monitor`` blocks;
    seen on this machine, reported for the lead): once every round is in ``metrics.jsonl``
    the run's results are complete, so after ``EXIT_GRACE_S`` the launcher is stopped and the
    run is recorded as ``hung_at_exit`` instead of blocking the sweep forever."""
    metrics = out_dir / "metrics.jsonl"
    with (out_dir / "fedhpg-run.stderr").open("w+") as stderr:
        process = subprocess.Popen(
            [
                str(BIN / "fedhpg-run"),
                *overrides,
                f"server.out_dir={out_dir}",
                f"hydra.run.dir={out_dir / 'hydra'}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=stderr,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        finished_at: float | None = None
        hung = False
        try:
            while process.poll() is None:
                time.sleep(0.5)
                if finished_at is None and metrics.exists():
                    if len(metrics.read_text().splitlines()) >= rounds:
                        finished_at = time.monotonic()
                elif finished_at is not None and time.monotonic() - finished_at > EXIT_GRACE_S:
                    hung = True
                    process.terminate()  # its children die with it
                    process.wait(timeout=30)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        if process.returncode != 0 and not hung:
            stderr.seek(0)
            raise RuntimeError(f"fedhpg-run failed: {stderr.read()[-2000:]}")
    return [json.loads(line) for line in metrics.read_text().splitlines()], hung


def run_one(plan: Plan, seed: int, kind: str) -> RunResult:
    overrides = overrides_for(plan, seed, kind)
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        records, hung = federation(overrides, Path(tmp), plan.rounds)
    wall = time.monotonic() - started - (EXIT_GRACE_S if hung else 0.0)
    evaluated = [r for r in records if "eval" in r]
    return RunResult(
        name=plan.name,
        kind=kind,
        seed=seed,
        overrides=overrides,
        trajectories=[r["trajectories_per_agent"] for r in evaluated],
        returns=[statistics.mean(e["return_mean"] for e in r["eval"].values()) for r in evaluated],
        initial=initial_return(overrides, plan.rounds),
        wall_s=wall,
        hung_at_exit=hung,
    )


def key(name: str, kind: str, seed: int) -> str:
    return f"{name}/{kind}/{seed}"


def load(path: Path) -> dict[str, RunResult]:
    if not path.exists():
        return {}
    return {k: RunResult(**v) for k, v in json.loads(path.read_text()).items()}


def save(path: Path, results: dict[str, RunResult]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".json.partial")
    data = {k: asdict(v) for k, v in sorted(results.items())}
    partial.write_text(json.dumps(data, indent=1) + "\n")
    partial.replace(path)


def _fmt(values: list[float]) -> str:
    return ", ".join(f"{v:,.1f}" for v in values)


def table(results: dict[str, RunResult]) -> str:
    lines = [
        "| env= | seeds | rounds | trajectories per agent | θ̃₀ greedy return "
        "| final greedy return | best evaluation | K = 1, final | threshold | wall per run (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for plan in PLANS.values():
        runs = [r for r in results.values() if r.name == plan.name and r.kind == "federation"]
        if not runs:
            continue
        runs.sort(key=lambda r: r.seed)
        singles = sorted(
            (r for r in results.values() if r.name == plan.name and r.kind == "single"),
            key=lambda r: r.seed,
        )
        single = _fmt([r.returns[-1] for r in singles]) if singles else "—"
        threshold = f"{plan.threshold:g}" if plan.threshold is not None else "none"
        walls = [r.wall_s for r in runs]
        hung = sum(r.hung_at_exit for r in runs + singles)
        hung_note = f" ({hung} hung at exit)" if hung else ""
        lines.append(
            f"| `{plan.name}` | {', '.join(str(r.seed) for r in runs)} | {plan.rounds} "
            f"| {runs[0].trajectories[-1]:,.0f} | {_fmt([r.initial for r in runs])} "
            f"| **{_fmt([r.returns[-1] for r in runs])}** | {_fmt([max(r.returns) for r in runs])} "
            f"| {single} | {threshold} | {results_file.span(walls)}{hung_note} |"
        )
    return "\n".join(lines)


def _federations(results: dict[str, RunResult], plan: Plan) -> list[RunResult]:
    runs = [r for r in results.values() if r.name == plan.name and r.kind == "federation"]
    return sorted(runs, key=lambda r: r.seed)


def _names(names: list[str]) -> str:
    return ", ".join(names[:-1]) + f" and {names[-1]}" if len(names) > 1 else "".join(names)


def summary(results: dict[str, RunResult]) -> str:
    """What the table says, from the runs: which presets end above their initial greedy return
    on every seed, which end at or above gymnasium's threshold on every seed (or on some), and
    which of those without a threshold end at the same return on every seed."""
    families = {plan.name: plan for plan in PLANS.values() if _federations(results, plan)}
    if not families:
        return "No run stored."

    def label(name: str) -> str:
        return f"`{name}`"

    improved = [
        n
        for n, plan in families.items()
        if all(r.returns[-1] > r.initial for r in _federations(results, plan))
    ]
    if len(improved) == len(families):
        sentence = "Every preset ends above its initial policy's greedy return on every seed"
    else:
        others = [n for n in families if n not in improved]
        sentence = (
            f"Every preset but {_names([label(n) for n in others])} ends above its initial "
            "policy's greedy return on every seed"
            if improved
            else "No preset ends above its initial policy's greedy return on every seed"
        )
        for name in others:
            below = [r for r in _federations(results, families[name]) if r.returns[-1] <= r.initial]
            plural = "s" if len(below) > 1 else ""
            sentence += (
                f"; {label(name)} ends at or below it on seed{plural} "
                f"{_names([str(r.seed) for r in below])} (best evaluation{plural} "
                f"{_names([f'{max(r.returns):,.1f}' for r in below])})"
            )
    every, some = [], []
    for name, plan in families.items():
        if plan.threshold is None:
            continue
        above = [r.returns[-1] >= plan.threshold for r in _federations(results, plan)]
        if all(above):
            every.append(label(name))
        elif any(above):
            some.append(label(name))
    if every:
        sentence += f"; {_names(every)} end at or above gymnasium's threshold on every seed"
    if some:
        sentence += f", {_names(some)} on some seeds"
    for name, plan in families.items():
        finals = {f"{r.returns[-1]:,.1f}" for r in _federations(results, plan)}
        if plan.threshold is not None or len(finals) != 1:
            continue
        (final,) = finals
        sentence += f"; {label(name)}'s greedy return ends at {final} on every seed"
    return sentence + "."


def tables(results: dict[str, RunResult]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(table(results), summary(results))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--only", choices=sorted(PLANS), nargs="*", default=None)
    parser.add_argument("--seeds", type=int, nargs="*", default=None)
    parser.add_argument("--no-single", action="store_true", help="skip the K=1 baselines")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument(
        "--tables-only",
        "--table-only",
        action="store_true",
        help="rebuild the table from the stored runs, stamped with their measurement",
    )
    args = parser.parse_args()
    results = load(args.results)
    if args.tables_only:
        print(table(results))
        results_file.rerender("presets", tables(results))
        return
    for name in args.only or list(PLANS):
        plan = PLANS[name]
        kinds = ["federation"] + (["single"] if plan.single_agent and not args.no_single else [])
        for seed in args.seeds if args.seeds is not None else plan.seeds:
            for kind in kinds:
                result = run_one(plan, seed, kind)
                results[key(name, kind, seed)] = result
                save(args.results, results)
                print(
                    f"{name} {kind} seed {seed}: greedy {result.initial:,.1f} → "
                    f"{result.returns[-1]:,.1f} after {result.trajectories[-1]:,.0f} "
                    f"trajectories per agent, {result.wall_s:.0f} s",
                    flush=True,
                )
    print(table(results))
    results_file.refresh(
        "presets", tables(results), results_file.command_line("benchmarks.presets")
    )


if __name__ == "__main__":
    main()
