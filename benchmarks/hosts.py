"""Agent hosts at scale: K logical agents on a few host processes (``agents.per_host``).

Start-up to the end of round 1, peak PSS of the whole federation, and the server's time per
round per participating agent (round time − the slowest host's wall time on the round, over
the agents that took part), from a real ``fedhpg-run`` federation on loopback.

    python -m benchmarks.hosts --agents 1000 --per-host 500 --rounds 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from benchmarks.runtime import _federation


def measure(agents: int, per_host: int, rounds: int, family: str, extra: list[str]) -> dict:
    overrides = [
        f"rounds={rounds}",
        f"env.family={family}",
        f"agents.num_agents={agents}",
        f"agents.per_host={per_host}",
        "agents.budget.batch_size=[2]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        "agents.virtual_clock=true",
        f"eval.every={rounds + 1}",
        "eval.episodes=1",
        "server.register_timeout_s=300",
        *extra,
    ]
    with tempfile.TemporaryDirectory() as tmp:
        records, first_round_s, peak = _federation(
            overrides, Path(tmp), sample_memory=True, poll_s=0.05
        )
    overhead = [
        (r["round_time_s"] - max(a["local_wall_s"] for a in r["agents"])) / len(r["agents"])
        for r in records
    ]
    return {
        "agents": agents,
        "per_host": per_host,
        "start_to_round_1_s": first_round_s,
        "peak_pss_mib": peak / 2**20,
        "round_time_s": [r["round_time_s"] for r in records],
        "server_us_per_agent_round": 1e6 * statistics.median(overhead),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--per-host", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--family", default="gridworld")
    parser.add_argument("extra", nargs="*")
    args = parser.parse_args()
    print(measure(args.agents, args.per_host, args.rounds, args.family, args.extra))
