"""The distributed runtime's costs: per-round coordination overhead against a bare pyzmq
broadcast-gather of the same payload, start-up time to the end of round 1, and memory.

Every figure comes from real ``fedhpg-run`` federations on loopback, started as subprocesses.
"""

from __future__ import annotations

import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.bare_zmq import broadcast_gather_ms

BIN = Path(sys.prefix) / "bin"
# CartPole MLPs with ~1e4 and ~1e6 parameters: 4·h + h + h·h + h + 2·h + 2.
HIDDEN_FOR = {10_000: 96, 1_000_000: 998}


@dataclass(frozen=True)
class OverheadResult:
    num_agents: int
    num_params: int
    overhead_ms: float
    """Median over rounds of round time − the slowest agent's local wall time."""
    between_rounds_ms: float
    """Median time between rounds outside the round itself (metrics, checkpoint, evaluation)."""
    bare_ms: float

    @property
    def target_ms(self) -> float:
        return 2 * self.bare_ms + 1.0


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as handle:
            return [int(p) for p in handle.read().split()]
    except FileNotFoundError:
        return []


def _pss_bytes(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as handle:
            for line in handle:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # the process ended between listing and reading
        pass
    return 0


def _federation(
    overrides: list[str],
    out_dir: Path,
    *,
    sample_memory: bool = False,
    poll_s: float = 0.01,
    env: dict[str, str] | None = None,
) -> tuple[list[dict], float, int]:
    """Run fedhpg-run; returns (metrics records, seconds to the end of round 1, peak PSS).

    ``poll_s`` is how often the metrics file and the memory are looked at: reading
    ``smaps_rollup`` of a dozen processes costs CPU, so long runs poll less often. ``env``:
    more environment variables for the federation's processes.
    """
    metrics = out_dir / "metrics.jsonl"
    started = time.monotonic()
    # stderr goes to a file, not a pipe: a long run's log would fill a pipe nobody reads yet.
    stderr = (out_dir / "fedhpg-run.stderr").open("w+")
    process = subprocess.Popen(
        [
            str(BIN / "fedhpg-run"),
            *overrides,
            f"server.out_dir={out_dir}",
            f"hydra.run.dir={out_dir / 'hydra'}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=stderr,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
    )
    first_round_s = float("nan")
    peak = 0
    try:
        while process.poll() is None:
            if first_round_s != first_round_s and metrics.exists() and metrics.read_text().strip():
                first_round_s = time.monotonic() - started
            if sample_memory:
                pids = [process.pid, *_children(process.pid)]
                peak = max(peak, sum(_pss_bytes(pid) for pid in pids))
            time.sleep(poll_s)
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        stderr.seek(0)
        log = stderr.read()
        stderr.close()
    if process.returncode != 0:
        raise RuntimeError(f"fedhpg-run failed: {log[-2000:]}")
    records = [json.loads(line) for line in metrics.read_text().splitlines()]
    return records, first_round_s, peak


def _common(num_agents: int, hidden: int, rounds: int) -> list[str]:
    return [
        f"rounds={rounds}",
        "env.family=cartpole",
        "env.level=0",
        # One-step episodes: the agents' compute stays tiny, so 8 processes on 2 cores do
        # not queue for the CPU and the figure is the coordination cost itself.
        "env.horizon=1",
        f"agents.num_agents={num_agents}",
        "agents.budget.batch_size=[1]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        f"policy.hidden=[{hidden},{hidden}]",
        f"eval.every={rounds}",
        "eval.episodes=1",
        "algo.step_size=0.001",
        "server.max_message_mb=64",
    ]


def coordination_overhead(num_agents: int, num_params: int, rounds: int = 30) -> OverheadResult:
    with tempfile.TemporaryDirectory() as tmp:
        records, _, _ = _federation(_common(num_agents, HIDDEN_FOR[num_params], rounds), Path(tmp))
    body = records[1:-1]  # round 1 warms caches; the last round also evaluates
    overhead = [r["round_time_s"] - max(a["local_wall_s"] for a in r["agents"]) for r in body]
    between = [
        (b["wall_time_s"] - a["wall_time_s"]) - b["round_time_s"]
        for a, b in itertools.pairwise(body)
    ]
    return OverheadResult(
        num_agents=num_agents,
        num_params=num_params,
        overhead_ms=1000 * statistics.median(overhead),
        between_rounds_ms=1000 * statistics.median(between),
        bare_ms=broadcast_gather_ms(num_agents, num_params),
    )


def startup_and_memory(num_agents: int = 8) -> tuple[float, float]:
    """(seconds from launching fedhpg-run to the end of round 1, peak total PSS in MiB) for the
    demo GridWorld with K agents."""
    overrides = [
        "rounds=40",
        f"agents.num_agents={num_agents}",
        "agents.budget.batch_size=[8]",
        "agents.budget.local_iters=[2]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0.0002]",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        _, first_round_s, peak = _federation(overrides, Path(tmp), sample_memory=True)
    return first_round_s, peak / 2**20


def table(results: list[OverheadResult]) -> str:
    lines = [
        "| K | parameters | fedhpg overhead per round (ms) | bare pyzmq+msgpack (ms) "
        "| target 2×bare+1 (ms) | between rounds: metrics+checkpoint (ms) |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.num_agents} | {r.num_params:,} | {r.overhead_ms:.2f} | {r.bare_ms:.2f} | "
        f"{r.target_ms:.2f} | {r.between_rounds_ms:.2f} |"
        for r in results
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    results = [coordination_overhead(k, n) for k in (2, 8) for n in (10_000, 1_000_000)]
    print(table(results))
    startup, memory = startup_and_memory(8)
    print(f"\nstart-up to end of round 1 (K=8): {startup:.2f} s; peak total PSS: {memory:.0f} MiB")
