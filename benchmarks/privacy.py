"""Privacy: what differential privacy costs in return, and what secure aggregation costs per
round (BENCHMARKS.md, "Privacy"). Each part writes its raw data and its table
(``benchmarks/results/tables/privacy_<part>.json``, rendered by ``python -m benchmarks.render``).

``--part utility``: CartPole, K = 100 agents (``agents=population``), 10 drawn uniformly each
round, 100 rounds, in process; non-private against ``privacy=dp`` at ε ∈ {1, 4, 8} against
readers of the released model (the sample secret from them) and the default
δ = min(1/(10K), 10⁻⁵) (σ calibrated to spend ε in the 100 rounds; adaptive clipping from
C = 10 towards the median norm, step 0.5; the noise and the sample seeded by
``privacy.noise_seed`` = the run's seed, so that the figures are reproducible), 5 seeds each
(``--seeds``); the greedy return of θ̃ (every agent's environment, 2 episodes each) every 10
rounds against trajectories per agent. Writes ``benchmarks/results/privacy_utility.json`` and
``docs/figures/privacy_utility.png``.

``--part overhead``: one secure aggregation of K agents' updates of d = 386 parameters (the
CartPole preset's 16-16 policy) with the protocol's own code (``common/privacy/secagg.py``),
timed per side on one thread, against a plain round of the same K agents in process; the
graph planned for corruption = dropout = γ (0.1, the default, and 0.05); every agent of the
round takes part, none drops out (and one setting where 10 % drop after sending their input).
Bytes each agent sends and receives are counted from the messages' arrays.
Writes ``benchmarks/results/privacy_overhead.json``.

``--part wire``: ``fedhpg-run`` on loopback (a server and two agent hosts; CartPole, B = 8,
every agent in every round), plain against ``privacy=secagg`` (corruption = dropout = 0.1 or
0.05): the median round time of rounds 2–6 at K = 10, 100 and 1,000. Writes
``benchmarks/results/privacy_wire.json``.

``python -m benchmarks.privacy --part utility|overhead|wire`` (each prints its table).
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import time
from datetime import date
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks import results_file
from fedhpg.common.privacy import accounting, fixedpoint, secagg, shamir
from fedhpg.common.privacy.contribution import EXTRA
from fedhpg.common.privacy.graph import Tolerance, plan_graph
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process

UTILITY = Path("benchmarks/results/privacy_utility.json")
OVERHEAD = Path("benchmarks/results/privacy_overhead.json")
WIRE = Path("benchmarks/results/privacy_wire.json")
FIGURE = Path("docs/figures/privacy_utility.png")
BASE = [
    "env=cartpole",
    "agents=population",
    "strategy.participation.mode=uniform",
    "strategy.participation.per_round=10",
    "rounds=100",
    "eval.every=10",
    "eval.episodes=2",
    "server.tensorboard=false",
]
DP = ["privacy=dp", "privacy.adaptive_clip=true", "privacy.clip=10", "privacy.clip_rate=0.5"]
EPSILONS = (1.0, 4.0, 8.0)


LEARNING = list(results_file.LEARNING_CODE)
FEDERATION = list(results_file.RUNTIME_CODE)
PARTS: dict[str, dict[str, Any]] = {
    "utility": {
        "title": "Privacy: what DP costs in return",
        "order": 220,
        "measures": [*LEARNING, "common/privacy", "server"],
        "data": UTILITY,
        "setup": (
            "CartPole, K = 100 (`agents=population`), 10 agents drawn a round (participation "
            "0.1), 100 rounds, in process; `privacy=dp` at the default δ = min(1/(10K), 10⁻⁵) = "
            "10⁻⁵, σ calibrated to spend exactly ε in the 100 rounds, adaptive clipping (the "
            "centred count) from C = 10 towards the median update norm (step 0.5), noise and "
            "sample seeded by `privacy.noise_seed` (reproducible); 5 seeds. Greedy return of θ̃ "
            "on every agent's environment (2 episodes each) every 10 rounds; the final one after "
            "round 100. Threat model: ε is against readers of the released model, the sample "
            "secret from them; a seeded run protects nothing, this measures what its σ costs. "
            "`make bench-privacy` runs all three parts."
        ),
        "summary": "The return of θ̃ after 100 rounds at each ε against the non-private run, "
        "with the same seeds.",
        "figure": {"path": str(FIGURE), "caption": "return against trajectories per agent"},
    },
    "overhead": {
        "title": "Privacy: secure aggregation's cost, the protocol alone",
        "order": 221,
        "measures": ["common/privacy"],
        "data": OVERHEAD,
        "setup": (
            "One secure aggregation of K updates of 386 parameters (the CartPole preset's "
            "policy) with the protocol's own code, every side on one thread, against a plain "
            "in-process round of the same K agents (B = 8). The graph and threshold are the plan "
            "for corruption = dropout = γ (0.1 is the default): k the neighbours each agent masks "
            "with (all the others up to 64 agents a round), t the shares that rebuild a secret; "
            "bytes count every array an agent sends and receives; a plain update sends 1,544 "
            "bytes."
        ),
        "summary": "What a secure round costs each agent and the server, in time and bytes, "
        "against a plain round of the same agents.",
    },
    "wire": {
        "title": "Privacy: secure aggregation's cost over the wire",
        "order": 222,
        "measures": ["common/privacy", *FEDERATION],
        "data": WIRE,
        "setup": (
            "`fedhpg-run env=cartpole agents=homogeneous10 agents.num_agents=K "
            "agents.budget.batch_size=[8] agents.per_host=K/2`, a server and two agent hosts on "
            "loopback, every agent in every round, plain against `privacy=secagg` at corruption "
            "= dropout = γ; median `round_time_s` of rounds 2–6."
        ),
        "summary": "The round time over loopback with and without secure aggregation.",
    },
}
"""Each part's section of BENCHMARKS.md."""


def report(
    part: str, data: dict[str, Any], summary: str | None = None, machine: str | None = None
) -> None:
    """A part's table as a result for BENCHMARKS.md, stamped with the run's date and commit."""
    spec = PARTS[part]
    printed = {"utility": utility_table, "overhead": overhead_table, "wire": wire_table}[part](data)
    extra = {"figure": spec["figure"]} if "figure" in spec else {}
    results_file.write(
        f"privacy_{part}",
        title=spec["title"],
        order=spec["order"],
        command=f"python -m benchmarks.privacy --part {part}",
        measures=spec["measures"],
        setup=spec["setup"],
        data=[str(spec["data"])],
        date=data["date"],
        commit_hash=data["commit"],
        machine_name=machine,
        tables=[results_file.table_from_markdown(printed, summary or spec["summary"], **extra)],
    )


def utility(seeds: int) -> dict[str, Any]:
    settings: dict[str, list[str]] = {"non-private": []}
    settings |= {f"ε = {eps:g}": [*DP, f"privacy.epsilon={eps}"] for eps in EPSILONS}
    results: dict[str, Any] = {}
    for label, extra in settings.items():
        runs = []
        for seed in range(seeds):
            curve: list[tuple[float, float]] = []
            last: dict[str, Any] = {}

            def record(row: Any, _: torch.Tensor, curve: list = curve, last: dict = last) -> None:
                if row.eval:
                    returns = [e.return_mean for e in row.eval.values()]
                    curve.append((row.trajectories_per_agent, float(np.mean(returns))))
                if row.privacy:
                    last.update(row.privacy)

            # seeded noise: the figures are reproducible (a utility measurement, not a
            # private run: seeded noise protects nothing)
            noise = [f"privacy.noise_seed={seed}"] if extra else []
            run = compose([*BASE, *extra, *noise, f"seed={seed}"])
            started = time.perf_counter()
            run_in_process(run, on_round=[record])
            runs.append(
                {
                    "seed": seed,
                    "curve": curve,
                    "seconds": time.perf_counter() - started,
                    "epsilon": last.get("epsilon"),
                    "noise_multiplier": last.get("noise_multiplier"),
                    "final_clip": last.get("clip"),
                }
            )
            logging.info("%s seed %d: final return %.1f", label, seed, curve[-1][1])
        results[label] = runs
    return {
        "command": "python -m benchmarks.privacy --part utility",
        "date": date.today().isoformat(),
        "commit": results_file.commit(),
        "overrides": BASE,
        "dp_overrides": DP,
        "delta": accounting.default_delta(100),
        "epsilon_against": "readers of the released model (the sample secret from them)",
        "results": results,
    }


def draw_utility(data: dict[str, Any]) -> None:
    from fedhpg.server.commands.plot import draw_band, figure_and_axis, legend, save

    figure, axis = figure_and_axis()
    for label, runs in data["results"].items():
        curves = [(np.array([p[0] for p in r["curve"]]), np.array([p[1] for p in r["curve"]]))
                  for r in runs]  # fmt: skip
        draw_band(axis, label, curves)
    axis.set_xlabel("trajectories per agent")
    axis.set_ylabel("greedy return of θ̃ (mean over the 100 agents)")
    axis.set_title("CartPole, K = 100, 10 agents a round: DP-FedAvg at δ = 1/K^1.1")
    axis.set_ylim(0, 560)
    legend(axis, "mean", loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the curves
    figure.set_size_inches(10, 4.5)
    save(figure, FIGURE)


def utility_table(data: dict[str, Any]) -> str:
    lines = [
        "| setting | σ | final return (mean over seeds) | per seed | best eval (mean) |",
        "|---|---|---|---|---|",
    ]
    for label, runs in data["results"].items():
        finals = [r["curve"][-1][1] for r in runs]
        best = [max(p[1] for p in r["curve"]) for r in runs]
        sigma = runs[0]["noise_multiplier"]
        lines.append(
            f"| {label} | {sigma:.3g} | {np.mean(finals):.1f} | "
            f"{', '.join(f'{f:.0f}' for f in finals)} | {np.mean(best):.1f} |"
            if sigma is not None
            else f"| {label} | — | {np.mean(finals):.1f} | "
            f"{', '.join(f'{f:.0f}' for f in finals)} | {np.mean(best):.1f} |"
        )
    return "\n".join(lines)


# --- overhead ---------------------------------------------------------------------------------

NUM_PARAMS = 386


def _plain_round_s(agents: int) -> float:
    """Seconds of one round of ``agents`` CartPole agents in process (the median of 3 after one
    warm-up), every agent selected."""
    from fedhpg.server.assembly import check_run
    from fedhpg.server.pools.inprocess import make_in_process_pool

    run = compose(
        [
            "env=cartpole",
            "agents=homogeneous10",
            f"agents.num_agents={agents}",
            "agents.budget.batch_size=[8]",
            "rounds=5",
        ]
    )
    checked = check_run(run, distributed=False)
    pool = make_in_process_pool(run)
    try:
        times = []
        for round_index in range(1, 5):
            started = time.perf_counter()
            pool.train(round_index, checked.initial_theta, list(range(agents)))
            times.append(time.perf_counter() - started)
        return float(np.median(times[1:]))
    finally:
        pool.close()


def secure_round(agents: int, tolerance: float, drop: float = 0.0) -> dict[str, Any]:
    """One secure aggregation of ``agents`` inputs, its graph planned for corruption = dropout
    = ``tolerance``: seconds per side, bytes per agent."""
    rng = np.random.default_rng(0)
    length = NUM_PARAMS + EXTRA
    scale = fixedpoint.scale_for(agents, 1e4)
    sides = {k: secagg.SecAggAgent(k) for k in range(agents)}
    plan = plan_graph(agents, Tolerance(corruption=tolerance, dropout=tolerance))
    setup = secagg.RoundSetup(
        round=1,
        participants=tuple(range(agents)),
        channel_keys={k: a.channel_public for k, a in sides.items()},
        mask_keys={k: side.advertise(1) for k, side in sides.items()},
        seed_commitments={k: side.seed_commitment(1) for k, side in sides.items()},
        length=length,
        neighbours=plan.neighbours,
        threshold=plan.threshold,
    )
    server = secagg.SecAggRound(setup)
    agent_s = server_s = 0.0
    dropped = set(rng.choice(agents, size=round(drop * agents), replace=False).tolist())
    sent = received = 0
    for k, side in sides.items():
        t = time.perf_counter()
        shares = side.share_keys(setup)
        agent_s += time.perf_counter() - t
        t = time.perf_counter()
        server.add_keys(k, shares)
        server_s += time.perf_counter() - t
        # its advert (mask key, seed commitment, signature) and its sealed shares; every advert
        sent += 32 + 32 + 64 + len(shares.sealed) * (secagg.SEALED_BYTES + 8)
        received += agents * (32 + 32 + 64)
    for k, side in sides.items():
        t = time.perf_counter()
        keys, sealed = server.routed(k)
        server_s += time.perf_counter() - t
        received += len(keys) * (32 + secagg.SEALED_BYTES + 8)
        words = fixedpoint.encode(rng.uniform(-1, 1, length), scale, 1e4)
        t = time.perf_counter()
        masked = side.mask(1, words, keys, sealed)
        agent_s += time.perf_counter() - t
        sent += 8 * length
        t = time.perf_counter()
        server.add_masked(k, masked)
        server_s += time.perf_counter() - t
    out, included = server.unmask_request()
    for k in included:
        received += 8 * (len(out) + len(included))
        if k in dropped:
            continue
        t = time.perf_counter()
        reveal = sides[k].reveal(1, out, included)
        agent_s += time.perf_counter() - t
        sent += len(reveal) * (shamir.SHARE_BYTES + 9)
        server.add_reveal(k, reveal)
    t = time.perf_counter()
    server.total()
    server_s += time.perf_counter() - t
    degree = len(setup.graph[0])
    return {
        "agents": agents,
        "tolerance": tolerance,
        "neighbours": degree,
        "threshold": setup.threshold_of(0),
        "dropped_after_input": len(dropped),
        "agent_s_each": agent_s / agents,
        "agents_s_total": agent_s,
        "server_s": server_s,
        "bytes_sent_each": sent / agents,
        "bytes_received_each": received / agents,
        "plain_bytes_each": 4 * NUM_PARAMS,
    }


def overhead() -> dict[str, Any]:
    cases = [(10, 0.1, 0.0), (100, 0.1, 0.0), (100, 0.1, 0.1), (100, 0.05, 0.0), (1000, 0.05, 0.0),
             (1000, 0.1, 0.0)]  # fmt: skip
    plain = {k: _plain_round_s(k) for k in sorted({c[0] for c in cases})}
    rows = []
    for agents, tolerance, drop in cases:
        row = secure_round(agents, tolerance, drop)
        row["plain_round_s"] = plain[agents]
        rows.append(row)
        logging.info("%s", row)
    return {
        "command": "python -m benchmarks.privacy --part overhead",
        "date": date.today().isoformat(),
        "commit": results_file.commit(),
        "num_params": NUM_PARAMS,
        "rows": rows,
    }


def overhead_table(data: dict[str, Any]) -> str:
    lines = [
        "| K | γ = δ | neighbours k (t) | dropped | plain round s | secure agg: agents' s (each) "
        "| server s | bytes sent / agent (plain) | bytes received / agent |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in data["rows"]:
        lines.append(
            f"| {r['agents']:,} | {r['tolerance']:g} | {r['neighbours']} ({r['threshold']}) | "
            f"{r['dropped_after_input']} | {r['plain_round_s']:.3f} | {r['agents_s_total']:.2f} "
            f"({1000 * r['agent_s_each']:.1f} ms) | {r['server_s']:.2f} | "
            f"{r['bytes_sent_each']:,.0f} ({r['plain_bytes_each']:,}) | "
            f"{r['bytes_received_each']:,.0f} |"
        )
    return "\n".join(lines)


# --- over the wire: fedhpg-run's round times ----------------------------------------------------

WIRE_CASES = ((10, 5, 0.1), (100, 50, 0.1), (100, 50, 0.05), (1000, 500, 0.05))
"""(K, agents per host, corruption = dropout): two agent hosts, every agent in every round."""


def wire() -> dict[str, Any]:
    """Median ``round_time_s`` of rounds 2–6 of ``fedhpg-run`` (a server and two agent hosts
    on loopback), plain and with ``privacy=secagg``, each agent in every round."""
    import sys
    import tempfile

    rows = []
    for agents, per_host, tolerance in WIRE_CASES:
        plan = plan_graph(agents, Tolerance(corruption=tolerance, dropout=tolerance))
        row: dict[str, Any] = {
            "agents": agents,
            "per_host": per_host,
            "tolerance": tolerance,
            "neighbours": plan.neighbours,
        }
        for mode in ("none", "secagg"):
            with tempfile.TemporaryDirectory() as directory:
                out = Path(directory) / "run"
                extra = [
                    f"privacy.secagg.corruption={tolerance}",
                    f"privacy.secagg.dropout={tolerance}",
                ]
                command = [
                    str(Path(sys.prefix) / "bin" / "fedhpg-run"),
                    "env=cartpole",
                    "agents=homogeneous10",
                    f"agents.num_agents={agents}",
                    "agents.budget.batch_size=[8]",
                    f"agents.per_host={per_host}",
                    "rounds=6",
                    "eval.every=100",
                    "eval.episodes=1",
                    "server.tensorboard=false",
                    f"privacy={mode}",
                    *(extra if mode == "secagg" else []),
                    f"server.out_dir={out}",
                    f"hydra.run.dir={out}",
                ]
                subprocess.run(command, check=True, capture_output=True, cwd=directory)
                lines = (out / "metrics.jsonl").read_text().splitlines()
                times = [json.loads(line)["round_time_s"] for line in lines][1:]
                row[mode] = float(np.median(times))
        rows.append(row)
        logging.info("%s", row)
    return {
        "command": "python -m benchmarks.privacy --part wire",
        "date": date.today().isoformat(),
        "commit": results_file.commit(),
        "rows": rows,
    }


def wire_table(data: dict[str, Any]) -> str:
    lines = [
        "| K | hosts × agents | γ = δ | neighbours | plain round s | secure round s | overhead s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in data["rows"]:
        lines.append(
            f"| {r['agents']:,} | 2 × {r['per_host']} | {r['tolerance']:g} | {r['neighbours']} | "
            f"{r['none']:.3f} | "
            f"{r['secagg']:.3f} | {r['secagg'] - r['none']:.3f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=("utility", "overhead", "wire"), required=True)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--plot-only", action="store_true", help="redraw from the stored results")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("fedhpg").setLevel(logging.WARNING)
    logging.getLogger("absl").setLevel(logging.ERROR)
    if args.part == "utility":
        if args.plot_only:
            data = json.loads(UTILITY.read_text())
        else:
            data = utility(args.seeds)
            UTILITY.write_text(json.dumps(data, indent=1))
        draw_utility(data)
        print(utility_table(data))
    elif args.part == "overhead":
        data = overhead()
        OVERHEAD.write_text(json.dumps(data, indent=1))
        print(overhead_table(data))
    else:
        data = wire()
        WIRE.write_text(json.dumps(data, indent=1))
        print(wire_table(data))
    if not args.plot_only:
        report(args.part, data)


if __name__ == "__main__":
    main()
