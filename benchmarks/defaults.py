"""The default settings at scale: ``fedhpg-run agents=population agents.num_agents=1000
rounds=2`` with no other override (``agents.per_host=auto`` picks the processes), timed from
launch to exit, with the peak PSS of its whole process tree (every 50 ms: the launcher, the
server and the agent hosts).

    python -m benchmarks.defaults                # 3 runs, results/defaults.json
    python -m benchmarks.defaults --runs 1 --agents 200

Run it at the lowest priority on a shared machine. The runs go to ``results/defaults.json``
(the median run's details beside every run's time and memory) and their table to
``results/tables/defaults.json`` (BENCHMARKS.md, ``python -m benchmarks.render``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import results_file
from benchmarks.runtime import BIN, _children, _pss_bytes

RESULTS = Path("benchmarks/results/defaults.json")
TITLE = "Defaults at K = 1,000"
MEASURES = [
    *results_file.RUNTIME_CODE,
    "common/learning/engine",
    "common/learning/batched",
    "common/heterogeneity/population.py",
    "conf",
]
SETUP = (
    "{runs} runs of `fedhpg-run agents=population agents.num_agents={agents} rounds={rounds}` "
    "with nothing else: `agents.per_host=auto` picks the agent hosts (two of 500 for 1,000 "
    "agents on a 2-core machine). PSS is the whole process tree's (launcher, server, hosts), "
    "sampled every 50 ms."
)


def _tree(pid: int) -> list[int]:
    found, queue = [], [pid]
    while queue:
        current = queue.pop()
        found.append(current)
        queue.extend(_children(current))
    return found


def measure(agents: int, rounds: int) -> dict[str, float | int | str]:
    command = [
        str(BIN / "fedhpg-run"),
        "agents=population",
        f"agents.num_agents={agents}",
        f"rounds={rounds}",
    ]
    with tempfile.TemporaryDirectory() as scratch:
        started = time.perf_counter()
        process = subprocess.Popen(
            command, cwd=scratch, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        peak = 0
        while process.poll() is None:
            peak = max(peak, sum(_pss_bytes(pid) for pid in _tree(process.pid)))
            time.sleep(0.05)
        seconds = time.perf_counter() - started
        stdout, stderr = process.communicate()
    table = [line for line in stdout.splitlines() if line.strip()]
    return {
        "command": "fedhpg-run " + " ".join(command[1:]),
        "exit_status": process.returncode,
        "seconds": seconds,
        "peak_pss_mib": peak / 2**20,
        "table_lines": len(table),
        "processes": stderr.count("registered host") or stderr.count("registered agent"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    runs = [measure(args.agents, args.rounds) for _ in range(args.runs)]
    for run in runs:
        print(
            f"exit {run['exit_status']}, {run['seconds']:.1f} s, peak PSS "
            f"{run['peak_pss_mib']:.0f} MiB, {run['table_lines']} lines of output",
            flush=True,
        )
    median = sorted(runs, key=lambda r: float(r["seconds"]))[len(runs) // 2]
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "commit": results_file.commit(),
        "median": median,
        "seconds": [r["seconds"] for r in runs],
        "peak_pss_mib": [r["peak_pss_mib"] for r in runs],
        "mean_seconds": statistics.fmean(float(r["seconds"]) for r in runs),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    report(runs, args.agents, args.rounds, " ".join(sys.argv[1:]))


def report(runs: list[dict[str, float | int | str]], agents: int, rounds: int, args: str) -> None:
    """The runs' table, as a result for BENCHMARKS.md."""
    seconds = ", ".join(f"{float(r['seconds']):.1f}" for r in runs)
    pss = ", ".join(f"{float(r['peak_pss_mib']):.0f}" for r in runs)
    statuses = ", ".join(str(r["exit_status"]) for r in runs)
    lines = sorted({int(r["table_lines"]) for r in runs})
    row = [seconds, pss, statuses, f"a {'/'.join(map(str, lines))}-line summary"]
    results_file.write(
        "defaults",
        title=TITLE,
        order=10,
        command=f"python -m benchmarks.defaults {args}".strip(),
        measures=MEASURES,
        setup=SETUP.format(runs=len(runs), agents=agents, rounds=rounds),
        data=[str(RESULTS)],
        tables=[
            {
                "columns": ["launch → exit (s)", "peak PSS (MiB)", "exit status", "output"],
                "rows": [row],
                "summary": f"K = {agents:,} with the defaults, launch to exit and the peak "
                "memory of the whole process tree, run by run.",
            }
        ],
    )


if __name__ == "__main__":
    main()
