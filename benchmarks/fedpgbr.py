"""FedPG-BR against 3 of 10 Byzantine agents on CartPole-v1 (its paper's Section 5 set-up):
fedhpg's FedPG-BR (algo=fedpgbr, strategy=fedpgbr) beside plain averaging (FedHPG, the server's
Adam on the mean of the agents' gradients, as FedPG-BR's baseline) and the coordinate-wise
median (the same with strategy.params.inner=median), agents 0-2 sending −2.5 × their gradient
(``sign_flip``) or adding uniform noise of 3 × its range (``random_noise``).

``experiment=k10_cartpole`` (B=16, H=500, γ=0.999, MLP 16-16, greedy evaluation of 10 episodes
per agent every 2 rounds), counted clock: every trajectory count deterministic, counted as
``trajectories_per_agent`` counts (FedPG-BR's server's own samples divided by K); server step
0.01. Each run ends once its mean greedy return held ≥ 475 for 5 evaluations, or at the
trajectory budget.

``python -m benchmarks.fedpgbr [--seeds 3] [--budget 1500]`` prints a table, writes
``docs/figures/fedpgbr_byzantine.png`` and keeps the curves in
``benchmarks/results/fedpgbr.json`` (``--plot-only`` redraws from them, ``--resume`` keeps them
and runs the missing ones).
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
from benchmarks.thresholds import TARGET

FIGURE = Path("docs/figures/fedpgbr_byzantine.png")
RESULTS = Path("benchmarks/results/fedpgbr.json")
SERVER_LR = 0.01
SUSTAINED = 5
"""A run ends once this many consecutive evaluations are ≥ TARGET."""
SETUP = ["experiment=k10_cartpole", "agents.clock=counted", "agents.step_delays_s=[0]"]
RULES = {
    "fedpgbr": ["algo=fedpgbr", "strategy=fedpgbr"],
    "mean": [],
    "median": ["strategy.params.inner=median"],
}
ATTACKS = ("sign_flip", "random_noise", "none")


@dataclass(frozen=True)
class Run:
    rule: str
    attack: str
    seed: int
    trajectories: list[float]
    returns: list[float]

    def final(self) -> float:
        return self.returns[-1] if self.returns else float("nan")

    def first(self) -> float | None:
        return next(
            (t for t, r in zip(self.trajectories, self.returns, strict=True) if r >= TARGET), None
        )


class _Stop(Exception):
    """Raised from the round callback: the return held, or the budget is spent."""


def run(rule: str, attack: str, seed: int, budget: int) -> Run:
    from fedhpg.server.commands import api

    trajectories: list[float] = []
    returns: list[float] = []

    def watch(record: Any, theta: Any) -> None:
        if record.eval is not None:
            trajectories.append(record.trajectories_per_agent)
            returns.append(statistics.mean(e.return_mean for e in record.eval.values()))
            if len(returns) >= SUSTAINED and min(returns[-SUSTAINED:]) >= TARGET:
                raise _Stop
        if record.trajectories_per_agent >= budget:
            raise _Stop

    attacked = [] if attack == "none" else [f"attack={attack}"]
    overrides = [
        *SETUP,
        *RULES[rule],
        *attacked,
        f"strategy.params.step_size={SERVER_LR}",
        f"seed={seed}",
        f"rounds={budget // 14 + 1}",  # a round spends ≥ 14 trajectories per agent
    ]
    with contextlib.suppress(_Stop):
        api.run(overrides=overrides, callbacks=[watch])
    return Run(rule, attack, seed, trajectories, returns)


def table(runs: list[Run]) -> str:
    lines = [
        f"| rule | attack (agents 0-2) | seeds | last greedy return, median (range) | "
        f"seeds reaching ≥ {TARGET:g} | trajectories/agent to first ≥ {TARGET:g} (median) |",
        "|---|---|---|---|---|---|",
    ]
    for attack in ATTACKS:
        for rule in RULES:
            group = [r for r in runs if (r.rule, r.attack) == (rule, attack)]
            if not group:
                continue
            finals = [r.final() for r in group]
            hits = [h for r in group if (h := r.first()) is not None]
            first = f"{statistics.median(hits):,.0f}" if hits else "never"
            lines.append(
                f"| {rule} | {attack} | {len(group)} | {statistics.median(finals):.1f} "
                f"({min(finals):.1f}–{max(finals):.1f}) | {len(hits)}/{len(group)} | {first} |"
            )
    return "\n".join(lines)


def plot(runs: list[Run], path: Path) -> None:
    """Each rule under each attack: the mean greedy return of each seed's curve (runs stop at
    their sustained point, so a curve ends where its run did)."""
    from fedhpg.server.commands.plot import figure_and_axis, save

    figure, axis = figure_and_axis()
    colours = {"fedpgbr": "tab:green", "mean": "tab:red", "median": "tab:blue"}
    styles = {"sign_flip": "-", "random_noise": "--", "none": ":"}
    for (rule, colour), (attack, style) in (
        (r, a) for r in colours.items() for a in styles.items()
    ):
        group = [r for r in runs if (r.rule, r.attack) == (rule, attack)]
        for index, one in enumerate(group):
            label = f"{rule}, {attack.replace('_', ' ')}" if index == 0 else None
            axis.plot(one.trajectories, one.returns, color=colour, linestyle=style, label=label)
    axis.axhline(TARGET, color="grey", linestyle="--", linewidth=1)
    axis.set_xlabel("trajectories per agent (FedPG-BR: + the server's b·N_t / K)")
    axis.set_ylabel("greedy return, mean over the agents' environments")
    axis.set_title("CartPole-v1, K=10, 3 Byzantine agents, server step 0.01")
    # one line per seed, not a mean with a band: runs end where they held 475
    axis.legend(loc="center right", fontsize=8, framealpha=0.9, title="one line per seed")
    path.parent.mkdir(parents=True, exist_ok=True)
    save(figure, path)


def load(path: Path = RESULTS) -> list[Run]:
    return [Run(**r) for r in json.loads(path.read_text())] if path.exists() else []


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--budget", type=int, default=1500)
    parser.add_argument("--attacks", nargs="+", choices=ATTACKS, default=list(ATTACKS))
    parser.add_argument("--rules", nargs="+", choices=list(RULES), default=list(RULES))
    parser.add_argument("--plot-only", action="store_true", help=f"redraw from {RESULTS}")
    parser.add_argument("--resume", action="store_true", help=f"keep the runs in {RESULTS}")
    args = parser.parse_args()
    runs = load() if args.plot_only or args.resume else []
    if not args.plot_only:
        done = {(r.rule, r.attack, r.seed) for r in runs}
        for seed in range(args.seeds):
            for attack in args.attacks:
                for rule in args.rules:
                    if (rule, attack, seed) in done:
                        continue
                    one = run(rule, attack, seed, args.budget)
                    print(f"{rule} {attack} seed {seed}: last {one.final():.1f}", flush=True)
                    runs.append(one)
                    RESULTS.parent.mkdir(parents=True, exist_ok=True)
                    RESULTS.write_text(json.dumps([asdict(r) for r in runs], indent=1))
    print(table(runs))
    plot(runs, FIGURE)
    if args.resume:
        print(f"{RESULTS} held earlier runs: the table is not stored as one run's result")
    elif not args.plot_only:
        summary = "Each aggregation rule under each attack by agents 0–2, over the seeds."
        results_file.refresh(
            "fedpgbr",
            [results_file.table_from_markdown(table(runs), summary)],
            results_file.command_line("benchmarks.fedpgbr"),
        )
    print(f"\nfigure: {FIGURE}; results: {RESULTS}")


if __name__ == "__main__":
    main()
