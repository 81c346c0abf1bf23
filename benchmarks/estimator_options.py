"""Estimator options on homogeneous CartPole-v1, K=10, in FedPG-BR's set-up (the one of
:mod:`benchmarks.learning`: B=16, H=500, γ=0.999, MLP 16-16, τ=1, agents' plain step 1, server
Adam via ``strategy=fedadam``, greedy evaluation of 10 episodes per agent every 2 rounds).

For each option set, server step size and seed: the trajectories per agent to the first
greedy return ≥ 475 (mean over agents) and to a *sustained* one, the first of 5 consecutive
evaluations ≥ 475. In process (``fedhpg.api.run``), which trains every agent as the distributed
runtime does; the figures count trajectories, so they do not depend on the machine's load.
A run stops once it is sustained, or at ``--max-trajectories`` per agent.

``python -m benchmarks.estimator_options [--seeds 5] [--server-lr 0.001 0.01] [--sets ...]``
prints a table and writes ``benchmarks/results/estimator_options.json`` (outcomes already
there are kept, not rerun; ``--table-only`` prints them).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from benchmarks import results_file
from benchmarks.learning import TARGET

RESULTS = Path("benchmarks/results/estimator_options.json")
SUSTAIN = 5  # consecutive evaluations ≥ TARGET
EVAL_EVERY = 2

# Each set replaces keys of the set-up; those with a B spend the same trajectories on more,
# noisier server steps (B per agent 8, 4, 2 or 1 instead of FedPG-BR's 16; with B = 1 the
# leave-one-out baseline is 0).
OPTION_SETS: dict[str, list[str]] = {
    "paper (eq. 6, mean baseline)": [],
    "normalize=batch": ["algo.normalize=batch"],
    "from_step + normalize=batch": ["algo.reward_to_go=from_step", "algo.normalize=batch"],
    "from_step": ["algo.reward_to_go=from_step"],
    "paper, B=8": ["agents.budget.batch_size=[8]"],
    "normalize=batch, B=8": ["algo.normalize=batch", "agents.budget.batch_size=[8]"],
    "paper, B=4": ["agents.budget.batch_size=[4]"],
    "normalize=batch, B=4": ["algo.normalize=batch", "agents.budget.batch_size=[4]"],
    "from_step + normalize=batch, B=4": [
        "algo.reward_to_go=from_step",
        "algo.normalize=batch",
        "agents.budget.batch_size=[4]",
    ],
    "paper, B=2": ["agents.budget.batch_size=[2]"],
    "normalize=batch, B=2": ["algo.normalize=batch", "agents.budget.batch_size=[2]"],
    "from_step + normalize=batch, B=2": [
        "algo.reward_to_go=from_step",
        "algo.normalize=batch",
        "agents.budget.batch_size=[2]",
    ],
    "paper, B=1 (baseline 0)": ["agents.budget.batch_size=[1]"],
    "normalize=batch, B=1": ["algo.normalize=batch", "agents.budget.batch_size=[1]"],
    "from_step, B=1": ["algo.reward_to_go=from_step", "agents.budget.batch_size=[1]"],
    "normalize=episode": ["algo.normalize=episode"],
}


ENGINE = "auto"
"""``algo.engine`` of the runs (``--engine``): the compiled engine by default;
``estimator_options_numpy.json`` holds the same study on the numpy engine."""


def setup_overrides(seed: int, rounds: int, server_lr: float) -> list[str]:
    """FedPG-BR's CartPole set-up (benchmarks/learning.py's run_curve, homogeneous)."""
    return [
        f"algo.engine={ENGINE}",
        f"seed={seed}",
        f"rounds={rounds}",
        "env=cartpole",
        "env.level=0",
        "env.gamma=0.999",
        "agents.num_agents=10",
        "agents.budget.batch_size=[16]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        "policy.hidden=[16,16]",
        "algo.estimator=gpomdp",
        "algo.optimizer=sgd",
        "algo.step_size=1.0",
        "strategy=fedadam",
        f"strategy.params.step_size={server_lr}",
        f"eval.every={EVAL_EVERY}",
        "eval.episodes=10",
    ]


@dataclass(frozen=True)
class Outcome:
    options: str
    server_lr: float
    seed: int
    first: float | None
    """Trajectories per agent at the first evaluation ≥ TARGET (None: not reached)."""
    sustained: float | None
    """At the first of SUSTAIN consecutive evaluations ≥ TARGET (None: not reached)."""
    trajectories: list[float]
    returns: list[float]


class _Sustained(Exception):
    """Raised from the round callback to end a run once its outcome is known."""


class _Watch:
    def __init__(self) -> None:
        self.trajectories: list[float] = []
        self.returns: list[float] = []

    def __call__(self, record: Any, _: Any) -> None:
        if record.eval:
            self.trajectories.append(record.trajectories_per_agent)
            self.returns.append(statistics.mean(e.return_mean for e in record.eval.values()))
            if sustained_at(self.trajectories, self.returns) is not None:
                raise _Sustained


def first_at(trajectories: list[float], returns: list[float]) -> float | None:
    return next((t for t, r in zip(trajectories, returns, strict=True) if r >= TARGET), None)


def sustained_at(trajectories: list[float], returns: list[float]) -> float | None:
    for i in range(len(returns) - SUSTAIN + 1):
        if all(r >= TARGET for r in returns[i : i + SUSTAIN]):
            return trajectories[i]
    return None


def overrides_of(label: str, seed: int, server_lr: float, max_trajectories: int) -> list[str]:
    """The set-up with the option set's keys replaced (Hydra refuses a key given twice)."""
    chosen = dict(item.split("=", 1) for item in OPTION_SETS[label])
    batch = int(chosen.get("agents.budget.batch_size", "[16]").strip("[]"))
    keys = dict(
        item.split("=", 1) for item in setup_overrides(seed, max_trajectories // batch, server_lr)
    )
    keys.update(chosen)
    return [f"{key}={value}" for key, value in keys.items()]


def run_one(label: str, server_lr: float, seed: int, max_trajectories: int) -> Outcome:
    from fedhpg.server.commands.api import run

    watch = _Watch()
    with contextlib.suppress(_Sustained):
        run(overrides=overrides_of(label, seed, server_lr, max_trajectories), callbacks=[watch])
    return Outcome(
        label,
        server_lr,
        seed,
        first_at(watch.trajectories, watch.returns),
        sustained_at(watch.trajectories, watch.returns),
        watch.trajectories,
        watch.returns,
    )


def _summary(values: list[float | None], cap: int) -> str:
    reached = [v for v in values if v is not None]
    if not reached:
        return f"none by {cap}"
    spread = f"{min(reached):.0f}–{max(reached):.0f}"
    # Seeds that never reached count as later than any that did.
    median = statistics.median(v if v is not None else float("inf") for v in values)
    if median == float("inf"):
        return f"none by {cap} ({len(reached)} of {len(values)} seeds: {spread})"
    text = f"{median:.0f} ({spread})"
    if len(reached) < len(values):
        text += f", {len(values) - len(reached)} seed(s) none by {cap}"
    return text


def _count(value: float | None) -> str:
    return "—" if value is None else f"{value:.0f}"


def table(outcomes: list[Outcome], cap: int) -> str:
    lines = [
        "| options | server Adam step | seeds | first ≥ 475: median (range) | sustained ≥ 475: "
        "median (range) | per seed (first / sustained) |",
        "|---|---|---|---|---|---|",
    ]
    order = list(OPTION_SETS)
    keys = sorted(
        dict.fromkeys((o.options, o.server_lr) for o in outcomes),
        key=lambda k: (k[1], order.index(k[0]) if k[0] in order else len(order)),
    )
    for label, lr in keys:
        group = [o for o in outcomes if (o.options, o.server_lr) == (label, lr)]
        per_seed = ", ".join(f"{_count(o.first)}/{_count(o.sustained)}" for o in group)
        lines.append(
            f"| {label} | {lr:g} | {len(group)} | {_summary([o.first for o in group], cap)} | "
            f"{_summary([o.sustained for o in group], cap)} | {per_seed} |"
        )
    return "\n".join(lines)


def write_outcomes(path: Path, outcomes: list[Outcome]) -> None:
    """One outcome per line, so a rerun's diff shows which runs changed."""
    lines = ",\n".join(json.dumps(asdict(o)) for o in outcomes)
    path.write_text(f"[\n{lines}\n]\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--server-lr", type=float, nargs="+", default=[0.001, 0.01])
    parser.add_argument("--sets", nargs="+", default=list(OPTION_SETS), choices=list(OPTION_SETS))
    parser.add_argument("--max-trajectories", type=int, default=1600)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--table-only", action="store_true", help="print the stored outcomes")
    parser.add_argument(
        "--engine",
        choices=["auto", "numpy"],
        default="auto",
        help="algo.engine (the outcomes differ by engine: give each its own --out)",
    )
    args = parser.parse_args()
    global ENGINE
    ENGINE = args.engine
    known = [Outcome(**o) for o in json.loads(args.out.read_text())] if args.out.exists() else []
    done = {(o.options, o.server_lr, o.seed) for o in known}
    outcomes = list(known)
    for label in [] if args.table_only else args.sets:
        for lr in args.server_lr:
            for seed in range(args.seeds):
                if (label, lr, seed) in done:
                    continue
                outcome = run_one(label, lr, seed, args.max_trajectories)
                print(
                    f"{label} lr={lr:g} seed={seed}: {outcome.first} / {outcome.sustained}",
                    flush=True,
                )
                outcomes.append(outcome)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                write_outcomes(args.out, outcomes)
    print(table(outcomes, args.max_trajectories))
    if known and not args.table_only:
        print(f"{args.out} held earlier outcomes: the table is not stored as one run's result")
    elif not args.table_only and args.out == RESULTS:
        summary = (
            "Trajectories per agent to the first and to a sustained greedy ≥ 475 for each "
            "estimator option and batch size, at both server steps."
        )
        results_file.refresh(
            "estimator_options",
            [results_file.table_from_markdown(table(outcomes, args.max_trajectories), summary)],
            results_file.command_line("benchmarks.estimator_options"),
        )


if __name__ == "__main__":
    main()
