"""Trajectories to the first and to a sustained greedy return ≥ 475 on CartPole-v1, K=10, in
FedPG-BR's set-up (B=16, H=500, γ=0.999, MLP 16-16, 10 greedy episodes per agent every 2
rounds): FedHPG, FedHPGVR and fedhpg's FedPG-BR at server step sizes 1e-3 and 1e-2, beside
the figures FedPG-BR's own code gave on this machine.

"Sustained" is 5 consecutive evaluations ≥ 475; its count is the trajectories at the first of
them. The trajectories are per agent, as FedPG-BR counts them: the agent's own, plus for
FedPG-BR the b·N_t the server samples in its inner loop (FedPG-BR's code adds B_t + b·N_t a
round). Runs are in process (the agents compute exactly what their processes would) on the
counted clock, so every count is deterministic and may be measured under load; a run stops
once sustained, or at the trajectory budget.

``python -m benchmarks.thresholds [--seeds 5] [--server-lr 0.001 0.01] [--algos ...]`` prints
the table and keeps every curve in ``benchmarks/results/thresholds.json`` (``--table-only``
prints the table from it, ``--resume`` keeps its curves and runs the missing ones);
``make bench-learning`` runs it after the learning curves.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

TARGET = 475.0
SUSTAINED = 5
RESULTS = Path("benchmarks/results/thresholds.json")
BUDGET = 3000
"""Trajectories per agent before a run that never sustains 475 is stopped."""
SETUP = [
    "env.family=cartpole",
    "env.level=0",
    "env.gamma=0.999",
    "agents=homogeneous10",
    "policy.hidden=[16,16]",
    "algo.estimator=gpomdp",
    "eval.every=2",
    "eval.episodes=10",
    "agents.clock=counted",
    "agents.virtual_clock=true",
    "agents.step_delays_s=[0]",
]
ALGOS: dict[str, list[str]] = {
    # plain steps of size 1 (θ_k − θ̃ = the agent's gradient), Adam on the server's average
    "fedhpg": ["algo=fedhpg", "algo.optimizer=sgd", "algo.step_size=1.0", "strategy=fedadam"],
    "fedhpgvr": ["algo=fedhpgvr", "algo.optimizer=sgd", "algo.step_size=1.0", "strategy=fedadam"],
    "fedpgbr": ["algo=fedpgbr", "strategy=fedpgbr"],
}
LABELS = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR", "fedpgbr": "FedPG-BR (fedhpg's)"}
PUBLISHED = {
    # FedPG-BR's own code on this machine, seeds 0 and 1: (first, sustained) per seed
    0.001: [(1068, 1196), (599, 1186)],
    0.01: [(221, 950), (225, 225)],
}
PRESET_RESULTS = Path("benchmarks/results/estimator_options.json")
"""The tuning runs of ``python -m benchmarks.estimator_options`` (the same set-up and rules)."""
BEST_PRESET = "paper, B=1 (baseline 0)"
"""Those runs' label of ``experiment=k10_cartpole_tuned``: the fewest trajectories found."""


@dataclass(frozen=True)
class Curve:
    algo: str
    server_lr: float
    seed: int
    trajectories: list[float]
    returns: list[float]

    def first(self) -> float | None:
        return next(
            (t for t, r in zip(self.trajectories, self.returns, strict=True) if r >= TARGET), None
        )

    def sustained(self) -> float | None:
        for i in range(len(self.returns) - SUSTAINED + 1):
            if all(r >= TARGET for r in self.returns[i : i + SUSTAINED]):
                return self.trajectories[i]
        return None


class _Stop(Exception):
    """Raised from the round callback to end a run: its return held, or its budget is spent."""


def run_curve(
    algo: str,
    server_lr: float,
    seed: int,
    budget: int = BUDGET,
    extra: Sequence[str] = (),
    engine: str = "auto",
) -> Curve:
    """One run of ``ALGOS[algo]`` (then the ``extra`` overrides) until sustained or
    ``budget`` trajectories per agent."""
    from fedhpg.server import api

    trajectories: list[float] = []
    returns: list[float] = []
    spent = 0.0

    def watch(record: Any, theta: Any) -> None:
        nonlocal spent
        line = record.to_json()
        spent += sum(a["trajectories"] for a in line["agents"]) / len(line["agents"])
        spent += line.get("strategy", {}).get("trajectories", 0)
        if "eval" in line:
            trajectories.append(spent)
            returns.append(statistics.mean(e["return_mean"] for e in line["eval"].values()))
            if len(returns) >= SUSTAINED and min(returns[-SUSTAINED:]) >= TARGET:
                raise _Stop
        if spent >= budget:
            raise _Stop  # the budget is spent: the curve ends here

    # a round spends ≥ 16 trajectories per agent: enough rounds for the budget
    overrides = [
        *SETUP,
        *ALGOS[algo],
        f"strategy.params.step_size={server_lr}",
        f"seed={seed}",
        f"rounds={budget // 16}",
        f"algo.engine={engine}",  # FedHPG's engine; FedHPGVR and FedPG-BR use the loop
        *extra,
    ]
    with contextlib.suppress(_Stop):
        api.run(overrides=overrides, callbacks=[watch])
    return Curve(algo, server_lr, seed, trajectories, returns)


def _spread(values: Sequence[float | None]) -> str:
    hits = [v for v in values if v is not None]
    if not hits:
        return "never"  # within the budget
    text = f"{statistics.median(hits):,.0f} ({min(hits):,.0f}–{max(hits):,.0f})"
    missed = len(values) - len(hits)
    return text + (f", {missed} never" if missed else "")


def table(curves: list[Curve], preset_results: Path = PRESET_RESULTS) -> str:
    lines = [
        f"| run | server step | seeds | trajectories/agent to first ≥ {TARGET:g}, median "
        f"(range) | to sustained ({SUSTAINED} evaluations) | source |",
        "|---|---|---|---|---|---|",
    ]
    for lr in sorted({c.server_lr for c in curves}):
        for algo in ALGOS:
            group = [c for c in curves if (c.algo, c.server_lr) == (algo, lr)]
            if group:
                first = _spread([c.first() for c in group])
                held = _spread([c.sustained() for c in group])
                lines.append(
                    f"| {LABELS[algo]} | {lr:g} | {len(group)} | {first} | {held} "
                    "| this benchmark |"
                )
        preset = [c for c in preset_curves(preset_results) if c.server_lr == lr]
        if preset:
            lines.append(
                f"| best preset (`experiment=k10_cartpole_tuned`: eq. 6, B=1) | {lr:g} | "
                f"{len(preset)} | {_spread([c.first() for c in preset])} | "
                f"{_spread([c.sustained() for c in preset])} | {preset_results} |"
            )
        if lr in PUBLISHED:
            firsts = [float(f) for f, _ in PUBLISHED[lr]]
            held = [float(s) for _, s in PUBLISHED[lr]]
            lines.append(
                f"| FedPG-BR, its own code | {lr:g} | 2 | {_spread(firsts)} | {_spread(held)} "
                "| published figures, seeds 0 and 1 |"
            )
    return "\n".join(lines)


def preset_curves(path: Path = PRESET_RESULTS) -> list[Curve]:
    """The tuned preset's curves from the estimator-options runs, counted by this module's
    first and sustained rules."""
    if not path.exists():
        return []
    return [
        Curve("preset", run["server_lr"], run["seed"], run["trajectories"], run["returns"])
        for run in json.loads(path.read_text())
        if run["options"] == BEST_PRESET
    ]


def load(path: Path = RESULTS) -> list[Curve]:
    return [Curve(**c) for c in json.loads(path.read_text())] if path.exists() else []


def save(curves: list[Curve], path: Path = RESULTS) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps([asdict(c) for c in curves], indent=1))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--server-lr", type=float, nargs="+", default=[0.001, 0.01])
    parser.add_argument("--algos", nargs="+", choices=list(ALGOS), default=list(ALGOS))
    parser.add_argument("--table-only", action="store_true", help=f"the table from {RESULTS}")
    parser.add_argument(
        "--resume", action="store_true", help=f"keep the curves already in {RESULTS}"
    )
    parser.add_argument("--results", type=Path, default=RESULTS, help="where the curves are kept")
    parser.add_argument(
        "--engine",
        choices=["auto", "numpy"],
        default="auto",
        help="algo.engine (FedHPG's curves differ by engine: give each its own --results)",
    )
    parser.add_argument(
        "--preset-results",
        type=Path,
        default=PRESET_RESULTS,
        help="the estimator-options runs the best preset's row is read from",
    )
    args = parser.parse_args(argv)
    curves = load(args.results) if args.resume or args.table_only else []
    if not args.table_only:
        done = {(c.algo, c.server_lr, c.seed) for c in curves}
        for lr in args.server_lr:
            for algo in args.algos:
                for seed in range(args.seeds):
                    if (algo, lr, seed) in done:  # kept from an earlier, interrupted run
                        continue
                    curve = run_curve(algo, lr, seed, engine=args.engine)
                    print(
                        f"{algo} lr={lr:g} seed {seed}: first {curve.first()}, sustained "
                        f"{curve.sustained()}",
                        flush=True,
                    )
                    curves.append(curve)
                    save(curves, args.results)
    print(table(curves, args.preset_results))


if __name__ == "__main__":
    main()
