"""Learning curves on homogeneous CartPole-v1 in FedPG-BR's set-up, through the distributed
runtime: K=10 (and K=1 beside it), B=16, H=500, γ=0.999, MLP 16-16, τ=1, greedy evaluation
over 10 episodes per agent. Agents take plain steps of size 1 (θ_k − θ̃ = their gradient) and
the server applies Adam to the average, as FedPG-BR's server does.

``python -m benchmarks.learning [--seeds 5] [--server-lr 0.01]`` prints a table and writes
``docs/figures/cartpole_learning.png``, then prints :mod:`benchmarks.thresholds`' tables
(trajectories per agent to a solved CartPole at server steps 1e-3 and 1e-2: fedhpg's rows,
run where not stored, beside FedPG-BR's own code's stored runs). ``--task lunarlander`` or
``--task halfcheetah`` runs the long benchmarks of :mod:`benchmarks.learning_long` instead
(the other arguments go there).

Every curve is kept in ``benchmarks/results/learning_cartpole.json``, and the two result
tables (``benchmarks/results/tables/learning_homogeneous.json`` and
``learning_heterogeneous.json``) are written from it; ``--tables-only`` writes them again from
that file alone, stamped with the date, commit and machine it was measured with (stored in it).
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks import results_file, thresholds
from benchmarks.runtime import _federation

TARGET = 475.0
FIGURE = Path("docs/figures/cartpole_learning.png")
HETEROGENEOUS_FIGURE = Path("docs/figures/cartpole_heterogeneous.png")
RESULTS = Path("benchmarks/results/learning_cartpole.json")
KINDS = ("homogeneous", "heterogeneous")


@dataclass(frozen=True)
class Curve:
    num_agents: int
    seed: int
    label: str
    trajectories: list[float]
    returns: list[float]
    wall_s: list[float]
    peak_pss_mib: float

    def first_reaching(self, target: float) -> tuple[float, float] | None:
        """(trajectories per agent, wall seconds) when the average greedy return first ≥ target."""
        for traj, ret, wall in zip(self.trajectories, self.returns, self.wall_s, strict=True):
            if ret >= target:
                return traj, wall
        return None


def run_curve(
    num_agents: int,
    seed: int,
    rounds: int,
    server_lr: float,
    *,
    algo: str = "fedhpg",
    level: float = 0.0,
    worst_agent: bool = False,
) -> Curve:
    """One federation; the curve is the mean (or, with ``worst_agent``, the minimum) over
    agents of the greedy return in each agent's own environment."""
    overrides = [
        f"seed={seed}",
        f"rounds={rounds}",
        f"algo.name={algo}",
        "++agents.budget.inner_steps=[2]",
        "++agents.budget.mini_batch_size=[8]",
        "env.family=cartpole",
        f"env.level={level}",
        "env.gamma=0.999",
        f"agents.num_agents={num_agents}",
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
        "eval.every=2",
        "eval.episodes=10",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        records, _, peak = _federation(overrides, Path(tmp), sample_memory=True)
    trajectories, returns, walls, total = [], [], [], 0.0
    for record in records:
        total += sum(a["trajectories"] for a in record["agents"]) / len(record["agents"])
        if "eval" in record:
            trajectories.append(total)
            per_agent = [e["return_mean"] for e in record["eval"].values()]
            returns.append(min(per_agent) if worst_agent else statistics.mean(per_agent))
            walls.append(record["wall_time_s"])
    label = f"{algo} K={num_agents}" + (f" level={level:g}" if level else "")
    return Curve(num_agents, seed, label, trajectories, returns, walls, peak / 2**20)


def plot(curves: list[Curve], path: Path, title: str, ylabel: str) -> None:
    """Mean over seeds and its 95% percentile-bootstrap band (the project's one convention,
    :mod:`fedhpg.server.commands.plot`), the target as a dashed line."""
    import numpy as np

    from fedhpg.server.commands.plot import draw_band, figure_and_axis, legend, save

    figure, axis = figure_and_axis()
    labels = list(dict.fromkeys(c.label for c in curves))
    for label, colour in zip(labels, ("tab:blue", "tab:orange", "tab:green"), strict=False):
        group = [c for c in curves if c.label == label]
        seeds = [(np.array(c.trajectories), np.array(c.returns)) for c in group]
        draw_band(axis, _readable(label), seeds, color=colour)
    axis.axhline(TARGET, color="grey", linestyle="--", linewidth=1, label=f"target {TARGET:g}")
    reached = [hit[0] for c in curves if (hit := c.first_reaching(TARGET))]
    if reached:
        axis.set_xlim(0, 2 * max(reached))
    axis.set_xlabel("trajectories per agent")
    axis.set_ylabel(ylabel)
    axis.set_title(title)
    legend(axis, "mean", loc="lower right")
    path.parent.mkdir(parents=True, exist_ok=True)
    save(figure, path)


def _readable(label: str) -> str:
    """ "fedhpgvr K=10 level=1" → "FedHPGVR, K=10, level 1"."""
    algo, *rest = label.split(" ")
    names = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR", "fedpgbr": "FedPG-BR"}
    return ", ".join([names.get(algo, algo), *(r.replace("level=", "level ") for r in rest)])


def table(curves: list[Curve]) -> str:
    lines = [
        "| run | seed | trajectories/agent to ≥475 | wall to ≥475 (s) | final return "
        "| peak PSS (MiB) |",
        "|---|---|---|---|---|---|",
    ]
    for curve in curves:
        hit = curve.first_reaching(TARGET)
        reached = f"{hit[0]:.0f} | {hit[1]:.1f}" if hit else "— | —"
        lines.append(
            f"| {curve.label} | {curve.seed} | {reached} | {curve.returns[-1]:.1f} | "
            f"{curve.peak_pss_mib:.0f} |"
        )
    return "\n".join(lines)


NAMES = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR", "fedpgbr": "FedPG-BR"}


def _group(kind: str, curve: Curve) -> str:
    """A table row's name: the agents of a homogeneous run, the algorithm of a heterogeneous."""
    if kind == "homogeneous":
        return f"homogeneous, K = {curve.num_agents}"
    algo = curve.label.split(" ")[0]
    return f"heterogeneous, {NAMES.get(algo, algo)}"


def _groups(kind: str, curves: list[Curve]) -> dict[str, list[Curve]]:
    groups: dict[str, list[Curve]] = {}
    for curve in curves:
        groups.setdefault(_group(kind, curve), []).append(curve)
    return {name: sorted(group, key=lambda c: c.seed) for name, group in groups.items()}


def _reached(group: list[Curve]) -> list[float | None]:
    return [hit[0] if (hit := c.first_reaching(TARGET)) else None for c in group]


def _median(group: list[Curve]) -> float | None:
    hits = [v for v in _reached(group) if v is not None]
    return statistics.median(hits) if hits else None


def summary_table(kind: str, curves: list[Curve]) -> str:
    """One row per run (agents or algorithm): seeds reaching the target, the median and each
    seed's trajectories per agent to it (the lowest median in bold), the peak memory."""
    lines = [
        f"| run | seeds reaching ≥ {TARGET:g} | trajectories per agent to ≥ {TARGET:g}, median "
        "(per seed) | peak PSS |",
        "|---|---|---|---|",
    ]
    groups = _groups(kind, curves)
    medians = {name: m for name, group in groups.items() if (m := _median(group)) is not None}
    best = min(medians.values()) if len(medians) > 1 else None
    for name, group in groups.items():
        reached = _reached(group)
        per_seed = ", ".join("—" if v is None else f"{v:.0f}" for v in reached)
        median = medians.get(name)
        text = "never" if median is None else f"{median:.0f}"
        if median is not None and median == best:
            text = f"**{text}**"
        memory = results_file.span(c.peak_pss_mib for c in group)
        hits = sum(v is not None for v in reached)
        lines.append(f"| {name} | {hits}/{len(group)} | {text} ({per_seed}) | {memory} MiB |")
    return "\n".join(lines)


def summary(kind: str, curves: list[Curve]) -> str:
    """Each run's median trajectories per agent to the target, and which runs miss it on a
    seed."""
    groups = _groups(kind, curves)
    where = "in every agent's environment" if kind == "heterogeneous" else "on average"
    medians = []
    missed = []
    for name, group in groups.items():
        run = name.split(", ", 1)[1]
        median = _median(group)
        medians.append(f"{run} in {'none' if median is None else f'{median:,.0f}'}")
        reached = _reached(group)
        if None in reached:
            missed.append(f"{run} misses it on {reached.count(None)} of {len(group)} seeds")
    text = (
        f"Median trajectories per agent to a greedy return ≥ {TARGET:g} {where}: "
        f"{', '.join(medians)}"
    )
    if missed:
        return text + f"; {', '.join(missed)}."
    return text + "; every run reaches it on every seed."


def tables(kind: str, curves: list[Curve]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(summary_table(kind, curves), summary(kind, curves))]


def save(curves: dict[str, list[Curve]], path: Path = RESULTS) -> None:
    """The curves of both kinds with the stamps of this measurement."""
    stamps = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "commit": results_file.commit(),
        "machine": results_file.machine(),
    }
    data = {**stamps, **{kind: [asdict(c) for c in found] for kind, found in curves.items()}}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) + "\n")


def load(path: Path = RESULTS) -> tuple[dict[str, str], dict[str, list[Curve]]]:
    """(the measurement's stamps, the curves of each kind) from ``path``."""
    data = json.loads(path.read_text())
    stamps = {key: data[key] for key in ("date", "commit", "machine")}
    return stamps, {kind: [Curve(**c) for c in data.get(kind, [])] for kind in KINDS}


def write_tables(curves: dict[str, list[Curve]], command: str | None = None) -> None:
    """Both result tables: from a run (``command``) stamped now, else from the stored file
    with its stamps."""
    for kind, found in curves.items():
        if not found:
            continue
        name = f"learning_{kind}"
        if command is not None:
            results_file.refresh(name, tables(kind, found), command, data=[str(RESULTS)])
        else:
            stamps, _ = load()
            results_file.rerender(name, tables(kind, found), stamps=stamps, data=[str(RESULTS)])


def main() -> None:
    task = argparse.ArgumentParser(add_help=False)
    task.add_argument("--task", default="cartpole")
    if task.parse_known_args()[0].task != "cartpole":
        from benchmarks import learning_long

        learning_long.main()
        return
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", choices=["cartpole"], default="cartpole")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--server-lr", type=float, default=0.01)
    parser.add_argument("--rounds-k10", type=int, default=40)
    parser.add_argument("--rounds-k1", type=int, default=200)
    # Every agent's environment must be solved, and FedHPGVR spends 2·B per round: 40 rounds
    # left a seed short of 475 in the worst agent's environment.
    parser.add_argument("--rounds-heterogeneous", type=int, default=80)
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help=f"only the result tables from {RESULTS}, stamped with its measurement",
    )
    args = parser.parse_args()
    if args.tables_only:
        if not RESULTS.exists():
            parser.error(f"--tables-only: no {RESULTS} (run the benchmark once)")
        write_tables(load()[1])
        return
    seeds = range(args.seeds)
    homogeneous = [run_curve(10, s, args.rounds_k10, args.server_lr) for s in seeds]
    homogeneous += [run_curve(1, s, args.rounds_k1, args.server_lr) for s in seeds]
    print(table(homogeneous), flush=True)
    plot(
        homogeneous,
        FIGURE,
        "Homogeneous CartPole-v1, server Adam (FedPG-BR set-up)",
        "greedy return (mean over agents, 10 episodes each)",
    )
    heterogeneous = [
        run_curve(
            10, s, args.rounds_heterogeneous, args.server_lr, algo=a, level=1.0, worst_agent=True
        )
        for a in ("fedhpg", "fedhpgvr")
        for s in seeds
    ]
    print(table(heterogeneous))
    plot(
        heterogeneous,
        HETEROGENEOUS_FIGURE,
        "Heterogeneous CartPole-v1 (pole half-length 0.1-0.9), K=10",
        "greedy return in the worst agent's environment",
    )
    print(f"\nfigures: {FIGURE}, {HETEROGENEOUS_FIGURE}")
    measured = {"homogeneous": homogeneous, "heterogeneous": heterogeneous}
    save(measured)
    write_tables(measured, results_file.command_line("benchmarks.learning"))
    # trajectories per agent to a solved CartPole at server steps 1e-3 and 1e-2, beside
    # FedPG-BR's own code (benchmarks/thresholds.py)
    print()
    thresholds.main(["--seeds", *(str(seed) for seed in range(args.seeds))])


if __name__ == "__main__":
    main()
