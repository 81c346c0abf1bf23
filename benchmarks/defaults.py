"""The default settings at scale: ``fedhpg-run agents=population agents.num_agents=1000
rounds=2`` with no other override (``agents.per_host=auto`` picks the processes), timed from
launch to exit, with the peak PSS of its whole process tree (every 50 ms: the launcher, the
server and the agent hosts).

    python -m benchmarks.defaults                # 3 runs, results/defaults.json
    python -m benchmarks.defaults --runs 1 --agents 200

Run it at the lowest priority on a shared machine; the figures it stores are the median run's.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks.runtime import BIN, _children, _pss_bytes

RESULTS = Path("benchmarks/results/defaults.json")


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
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    median = sorted(runs, key=lambda r: float(r["seconds"]))[len(runs) // 2]
    result = {
        "date": time.strftime("%Y-%m-%d"),
        "commit": commit,
        "median": median,
        "seconds": [r["seconds"] for r in runs],
        "peak_pss_mib": [r["peak_pss_mib"] for r in runs],
        "mean_seconds": statistics.fmean(float(r["seconds"]) for r in runs),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
