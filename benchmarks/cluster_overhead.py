"""What placing a federation on a cluster engine costs: ``fedhpg-cluster`` on SLURM and on Ray
against ``fedhpg-run`` on loopback, for the same runs.

Each run is timed from outside: start-up is the time from the command's start to the start of
round 1 (the first row of metrics.jsonl seen, less that round's own time), per round the
server's own clock over the rounds after the first (its ``wall_time_s``), the end the time from
the last row to the command's exit. The clusters are the two-node ones of ``make test-cluster``
(``cluster/slurm.sh``, ``cluster/ray.sh``: each node a network namespace of this machine), started
here if none runs and stopped again; ``fedhpg-run`` runs on this machine's loopback.

    python -m benchmarks.cluster_overhead                     # both cases, every engine, twice
    python -m benchmarks.cluster_overhead --cases demo --engines run,ray --repeats 1

Results in benchmarks/results/cluster_overhead.json, the table on stdout and in
benchmarks/results/tables/cluster_overhead.json (BENCHMARKS.md "Clusters"). The machine is
shared: the load average is recorded beside every run.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks import results_file

ROOT = Path(__file__).parents[1]
BIN = Path(sys.executable).parent
SCRIPTS = {"slurm": ROOT / "cluster" / "slurm.sh", "ray": ROOT / "cluster" / "ray.sh"}
CASES = {
    "demo": ["rounds=20"],
    "k1000": [
        "agents=population", "agents.num_agents=1000", "agents.per_host=500", "rounds=10",
        "server.register_timeout_s=600",
    ],
}  # fmt: skip
"""The demo (the default run: 4 heterogeneous GridWorld agents, one process each) cut to 20
rounds, and K = 1,000 on 2 agent hosts of 500, 10 rounds."""
COMMON = ["server.tensorboard=false"]
POLL_S = 0.02
TIMEOUT_S = 900.0
SETUP = (
    "The same runs through `fedhpg-run` on loopback, `fedhpg-cluster cluster=slurm` and "
    "`fedhpg-cluster cluster=ray` on the two-node clusters of `make test-cluster` (each node a "
    "network namespace of this machine, so every engine shares the same cores), the engines "
    "interleaved. demo: the default run (4 GridWorld agents with their emulated devices, one "
    "process each) for 20 rounds; k1000: `agents=population agents.num_agents=1000 "
    "agents.per_host=500`, 10 rounds, 2 agent hosts. Start-up: from the command's start to the "
    "start of round 1; per round: the server's clock over rounds 2 to the last; end: from the "
    "last round to the command's exit. Median of the runs (range); load: the 1-minute load "
    "average at the start, from other work on the same machine. `make bench-cluster` runs it."
)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _start(kind: str) -> tuple[dict[str, str], bool]:
    result = subprocess.run(
        ["bash", str(SCRIPTS[kind]), "start", "2"], capture_output=True, text=True, timeout=1200
    )
    if result.returncode != 0:
        raise SystemExit(f"{kind}: {result.stderr.strip().splitlines()[-1]}")
    values = dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)
    return values, "STARTED" in values


def _command(engine: str, case: str, run_dir: Path, clusters: dict[str, dict[str, str]]) -> tuple:
    keys = [*CASES[case], *COMMON, f"server.out_dir={run_dir}"]
    if engine == "run":
        hydra = f"hydra.run.dir={run_dir.parent / 'hydra'}"
        return [str(BIN / "fedhpg-run"), *keys, f"server.port={_free_port()}", hydra], {}
    values = clusters[engine]
    env = {k: values[k] for k in ("SLURM_CONF", "RAY_ADDRESS") if k in values}
    client = ["nsenter", f"--net=/run/netns/{values['NETNS']}"]
    return [*client, str(BIN / "fedhpg-cluster"), f"cluster={engine}", *keys], env


def measure(engine: str, case: str, clusters: dict[str, dict[str, str]]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="fedhpg-bench-") as tmp:
        run_dir = Path(tmp) / "run"
        command, env = _command(engine, case, run_dir, clusters)
        metrics = run_dir / "metrics.jsonl"
        load = os.getloadavg()[0]
        began = time.monotonic()
        process = subprocess.Popen(
            command, env={**os.environ, **env, "FEDHPG_LOG_LEVEL": "WARNING"},
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        first_seen = last_seen = None
        rows = 0
        while process.poll() is None and time.monotonic() - began < TIMEOUT_S:
            if metrics.exists():
                lines = metrics.read_text().count("\n")
                if lines > rows:
                    rows, last_seen = lines, time.monotonic()
                    first_seen = first_seen or last_seen
            time.sleep(POLL_S)
        if process.poll() is None:
            process.kill()
        _, stderr = process.communicate()
        ended = time.monotonic()
        if process.returncode != 0:
            raise SystemExit(f"{engine} {case}: exit {process.returncode}: {stderr[-2000:]}")
        records = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert first_seen is not None and last_seen is not None
    if len(records) > rows:  # rows written after the last poll: seen at the exit
        last_seen = ended
    walls = [r["wall_time_s"] for r in records]
    return {
        "engine": engine,
        "case": case,
        "rounds": len(records),
        "start_s": round(first_seen - began - records[0]["round_time_s"], 2),
        "per_round_s": round((walls[-1] - walls[0]) / (len(walls) - 1), 4),
        "end_s": round(ended - last_seen, 2),
        "total_s": round(ended - began, 2),
        "load_1min": round(load, 2),
    }


def _spread(values: list[float], digits: int) -> str:
    """The median, and the range where the values differ."""
    low, mid, high = min(values), statistics.median(values), max(values)
    text = f"{mid:.{digits}f}"
    return text if low == high else f"{text} ({low:.{digits}f}–{high:.{digits}f})"


def table(results: list[dict[str, Any]]) -> str:
    """One line per case and engine: medians over the repeats (their range in brackets) and
    the difference of the medians from fedhpg-run's."""
    lines = [
        "| run | engine | runs | start-up (s) | over fedhpg-run | per round (s) "
        "| over fedhpg-run | end (s) | load |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    names = {"run": "fedhpg-run (loopback)", "slurm": "cluster=slurm", "ray": "cluster=ray"}
    keys = ("start_s", "per_round_s", "end_s", "load_1min")
    for case in CASES:
        mine = [r for r in results if r["case"] == case]
        values = {
            engine: {k: [r[k] for r in mine if r["engine"] == engine] for k in keys}
            for engine in dict.fromkeys(r["engine"] for r in mine)
        }
        median = {e: {k: statistics.median(v[k]) for k in keys} for e, v in values.items()}
        base = median.get("run")

        for engine, m in median.items():
            over_start = f"{m['start_s'] - base['start_s']:+.1f}" if base else "–"
            over_round = f"{m['per_round_s'] - base['per_round_s']:+.2f}" if base else "–"
            lines.append(
                f"| {case} | {names[engine]} | {len(values[engine]['start_s'])} "
                f"| {_spread(values[engine]['start_s'], 1)} | {over_start} "
                f"| {_spread(values[engine]['per_round_s'], 2)} | {over_round} "
                f"| {_spread(values[engine]['end_s'], 1)} | {m['load_1min']:.1f} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--engines", default="run,slurm,ray")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--results", default=str(ROOT / "benchmarks/results/cluster_overhead.json"))
    parser.add_argument("--table", action="store_true", help="only print the stored results")
    args = parser.parse_args()
    if args.table:
        print(table(json.loads(Path(args.results).read_text())["runs"]))
        return
    cases, engines = args.cases.split(","), args.engines.split(",")
    clusters: dict[str, dict[str, str]] = {}
    started: list[str] = []
    try:
        for engine in engines:
            if engine != "run":
                clusters[engine], ours = _start(engine)
                started += [engine] if ours else []
        results = []
        for repeat in range(args.repeats):
            for case in cases:
                for engine in engines:  # interleaved: a drift of the load hits every engine
                    results.append({**measure(engine, case, clusters), "repeat": repeat})
                    print(json.dumps(results[-1]), file=sys.stderr)
    finally:
        for engine in started:
            subprocess.run(["bash", str(SCRIPTS[engine]), "stop"], timeout=300, check=False)
    record = {"date": time.strftime("%Y-%m-%d"), "commit": results_file.commit(), "runs": results}
    Path(args.results).write_text(json.dumps(record, indent=2) + "\n")
    print(table(results))
    report(record, f"python -m benchmarks.cluster_overhead --repeats {args.repeats}")


def report(
    record: dict[str, Any], command: str, summary: str | None = None, machine: str | None = None
) -> None:
    """The runs' table as a result for BENCHMARKS.md, stamped with the runs' date and commit."""
    results_file.write(
        "cluster_overhead",
        title="Clusters: fedhpg-cluster on SLURM and on Ray",
        order=240,
        command=command,
        measures=["cluster", "server"],
        setup=SETUP,
        data=["benchmarks/results/cluster_overhead.json"],
        date=record["date"],
        commit_hash=record["commit"],
        machine_name=machine,
        tables=[
            results_file.table_from_markdown(
                table(record["runs"]),
                summary
                or "Each cluster engine's start-up, per-round and end times against fedhpg-run's.",
            )
        ],
    )


if __name__ == "__main__":
    main()
