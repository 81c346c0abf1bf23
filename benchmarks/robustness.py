"""Robust strategies against FedPG-BR's sign-flip attack, through real ``fedhpg-run``
federations: homogeneous CartPole-v1, K=10 (B=16, H=500, γ=0.999, MLP 16-16), 3 of the 10
agents send −2.5 × their update (``attack=sign_flip``, agents 0-2).

Agents take τ=3 local Adam steps (step 0.01, reset every round) so that each strategy alone
is the whole server: ``mean`` (the paper), ``median`` and ``trimmed_mean`` (β = 0.3, so that
3 attackers of 10 can all be trimmed from one side), each with and without the attack.
Greedy evaluation, 10 episodes per agent every 2 rounds; the curve is the mean over agents.

``python -m benchmarks.robustness [--seeds 3] [--rounds 30]`` prints a table and writes
``docs/figures/robustness.png``, ``benchmarks/results/robustness.json`` (the curves) and
``benchmarks/results/tables/robustness.json`` (the table, for BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from benchmarks import results_file
from benchmarks.runtime import _federation

TARGET = 400.0
FIGURE = Path("docs/figures/robustness.png")
RESULTS = Path("benchmarks/results/robustness.json")
STRATEGIES = {
    "mean": ["strategy=mean"],
    "median": ["strategy=median"],
    "trimmed_mean": ["strategy=trimmed_mean", "strategy.params.trim_fraction=0.3"],
}
SETUP = [
    "env.family=cartpole",
    "env.level=0",
    "env.gamma=0.999",
    "agents=homogeneous10",
    "agents.budget.local_iters=[3]",
    "policy.hidden=[16,16]",
    "algo.estimator=gpomdp",
    "algo.optimizer=adam",
    "algo.step_size=0.01",
    "eval.every=2",
    "eval.episodes=10",
]


@dataclass(frozen=True)
class Curve:
    strategy: str
    attack: str
    seed: int
    trajectories: list[float]
    returns: list[float]
    wall_s: float

    @property
    def final(self) -> float:
        return self.returns[-1]

    def first_reaching(self, target: float) -> float | None:
        return next(
            (t for t, r in zip(self.trajectories, self.returns, strict=True) if r >= target), None
        )


def run_curve(strategy: str, attack: str, seed: int, rounds: int) -> Curve:
    overrides = [*SETUP, *STRATEGIES[strategy], f"seed={seed}", f"rounds={rounds}"]
    if attack != "none":
        overrides.append(f"attack={attack}")
    with tempfile.TemporaryDirectory() as tmp:
        records, _, _ = _federation(overrides, Path(tmp), poll_s=0.5)
    evaluated = [r for r in records if "eval" in r]
    return Curve(
        strategy=strategy,
        attack=attack,
        seed=seed,
        trajectories=[r["trajectories_per_agent"] for r in evaluated],
        returns=[statistics.mean(e["return_mean"] for e in r["eval"].values()) for r in evaluated],
        wall_s=records[-1]["wall_time_s"],
    )


def table(curves: list[Curve]) -> str:
    lines = [
        f"| strategy | attack | seeds | final greedy return (min–max) | seeds ≥ {TARGET:g} at the "
        f"end | trajectories/agent to first ≥ {TARGET:g} (median) |",
        "|---|---|---|---|---|---|",
    ]
    for strategy in STRATEGIES:
        for attack in ("none", "sign_flip"):
            group = [c for c in curves if (c.strategy, c.attack) == (strategy, attack)]
            if not group:
                continue
            finals = [c.final for c in group]
            hits = [h for c in group if (h := c.first_reaching(TARGET)) is not None]
            first = f"{statistics.median(hits):.0f}" if hits else "never"
            lines.append(
                f"| {strategy} | {attack} | {len(group)} | {statistics.median(finals):.1f} "
                f"({min(finals):.1f}–{max(finals):.1f}) | "
                f"{sum(f >= TARGET for f in finals)}/{len(group)} | {first} |"
            )
    return "\n".join(lines)


DESCRIPTION = (
    "Real `fedhpg-run` federations, homogeneous CartPole, K = 10, B = 16, γ = 0.999, 16-16 MLP; "
    "agents 0–2 send −2.5 × their update (`attack=sign_flip`); τ = 3 local Adam steps of 0.01; "
    "`trimmed_mean` with β = 0.3; {rounds} rounds, seeds {seeds}. `make bench-robustness` runs it."
)


def report(curves: list[Curve], rounds: int, summary: str | None = None, **stamp: Any) -> None:
    """The table as a result for BENCHMARKS.md; ``stamp`` gives ``date``, ``commit_hash`` and
    ``machine_name`` where they are not this run's."""
    seeds = sorted({c.seed for c in curves})
    results_file.write(
        "robustness",
        title="Robust strategies against sign-flipping agents",
        order=120,
        command="python -m benchmarks.robustness"
        + (f" --seeds {len(seeds)}" if len(seeds) != 3 else "")
        + (f" --rounds {rounds}" if rounds != 30 else ""),
        measures=[
            *results_file.LEARNING_CODE,
            *results_file.RUNTIME_CODE,
            "common/learning/attacks.py",
            "common/learning/byzantine_filter.py",
        ],
        setup=DESCRIPTION.format(rounds=rounds, seeds=", ".join(map(str, seeds))),
        data=[str(RESULTS)],
        tables=[
            results_file.table_from_markdown(
                table(curves),
                summary
                or "Each strategy with and without the sign-flipping agents, over the seeds.",
                figure={"path": str(FIGURE), "caption": "greedy return against trajectories"},
            )
        ],
        **stamp,
    )


def plot(curves: list[Curve], path: Path) -> None:
    """Each strategy with and without the attack: the mean over seeds and its 95%
    percentile-bootstrap band (the project's one convention, :mod:`fedhpg.server.commands.plot`)."""
    import numpy as np

    from fedhpg.server.commands.plot import draw_band, figure_and_axis, legend, save

    figure, axis = figure_and_axis()
    colours = {"mean": "tab:red", "median": "tab:blue", "trimmed_mean": "tab:green"}
    for strategy, colour in colours.items():
        for attack, style in (("none", ":"), ("sign_flip", "-")):
            group = [c for c in curves if (c.strategy, c.attack) == (strategy, attack)]
            if not group:
                continue
            seeds = [(np.array(c.trajectories), np.array(c.returns)) for c in group]
            label = f"{strategy}, {'3 sign-flippers' if attack != 'none' else 'no attack'}"
            draw_band(axis, label, seeds, color=colour, linestyle=style, band_alpha=0.12)
    axis.axhline(TARGET, color="grey", linestyle="--", linewidth=1)
    axis.set_xlabel("trajectories per agent")
    axis.set_ylabel("greedy return, mean over the agents' environments")
    axis.set_title("CartPole-v1, K=10, 3 agents send −2.5 × their update")
    legend(axis, "mean", loc="center right", fontsize=8, framealpha=0.9)
    path.parent.mkdir(parents=True, exist_ok=True)
    save(figure, path)


def load(path: Path) -> list[Curve]:
    """The curves a previous run stored (``--plot-only`` redraws the figure from them)."""
    return [Curve(**curve) for curve in json.loads(path.read_text())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--plot-only", action="store_true", help=f"redraw from {RESULTS}")
    args = parser.parse_args()
    if args.plot_only:
        curves = load(RESULTS)
        print(table(curves))
        plot(curves, FIGURE)
        print(f"\nfigure: {FIGURE}")
        return
    curves = []
    for seed in range(args.seeds):
        for strategy in STRATEGIES:
            for attack in ("none", "sign_flip"):
                curve = run_curve(strategy, attack, seed, args.rounds)
                print(
                    f"{strategy} {attack} seed {seed}: final {curve.final:.1f} "
                    f"({curve.wall_s:.0f} s)",
                    flush=True,
                )
                curves.append(curve)
    print(table(curves))
    plot(curves, FIGURE)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps([asdict(c) for c in curves], indent=1))
    report(curves, args.rounds)
    print(f"\nfigure: {FIGURE}; results: {RESULTS}")


if __name__ == "__main__":
    main()
