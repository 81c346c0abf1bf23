"""The distributed runtime's costs: per-round coordination overhead against a bare pyzmq
broadcast-gather of the same payload, start-up time to the end of round 1, and memory.

Every figure comes from real ``fedhpg-run`` federations on loopback, started as subprocesses.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from benchmarks import results_file
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
    """Median server wall time between two rounds, outside both (the previous round's metrics
    line, TensorBoard event and checkpoint are written while the agents train: inside the
    next round, overlapped with its compute)."""
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
    command: list[str] | None = None,
    watch: Callable[[int, Path], None] | None = None,
) -> tuple[list[dict], float, int]:
    """Run fedhpg-run; returns (metrics records, seconds to the end of round 1, peak PSS).

    ``poll_s`` is how often the metrics file and the memory are looked at: reading
    ``smaps_rollup`` of a dozen processes costs CPU, so long runs poll less often. ``env``:
    more environment variables for the federation's processes; ``command``: what starts the
    federation instead of this environment's ``fedhpg-run`` (another commit's, say);
    ``watch(pid, metrics)``: run in a thread of its own while the federation runs (its
    launcher's pid and the metrics file it appends to), joined before this returns.
    """
    metrics = out_dir / "metrics.jsonl"
    started = time.monotonic()
    # stderr goes to a file, not a pipe: a long run's log would fill a pipe nobody reads yet.
    stderr = (out_dir / "fedhpg-run.stderr").open("w+")
    process = subprocess.Popen(
        [
            *(command or [str(BIN / "fedhpg-run")]),
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
    watcher = None
    if watch is not None:
        watcher = threading.Thread(target=watch, args=(process.pid, metrics), daemon=True)
        watcher.start()
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
        if watcher is not None:
            watcher.join()
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
        "| target 2×bare+1 (ms) | between rounds (ms) |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.num_agents} | {r.num_params:,} | {r.overhead_ms:.2f} | {r.bare_ms:.2f} | "
        f"{r.target_ms:.2f} | {r.between_rounds_ms:.2f} |"
        for r in results
    ]
    return "\n".join(lines)


CELLS = [(k, n) for k in (2, 8) for n in (10_000, 1_000_000)]
"""(K, parameters) of each row of the table."""


def summary(runs: list[list[OverheadResult]]) -> str:
    """What the table says, from its medians over the runs."""

    def extra_ms(cell: int) -> float:
        return statistics.median(run[cell].overhead_ms - run[cell].bare_ms for run in runs)

    small = [CELLS.index((k, 10_000)) for k in (2, 8)]
    return (
        f"At 10⁴ parameters a round costs {extra_ms(small[0]):.1f} ms (K = 2) and "
        f"{extra_ms(small[1]):.1f} ms (K = 8) more than bare pyzmq exchanging the same vectors "
        "(medians over the runs); at K = 8 on 2 cores the agent processes queue for the cores, "
        "which the bare peers never do."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs of every cell (≥ 1)")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    runs: list[list[OverheadResult]] = []
    starts: list[tuple[float, float]] = []
    for repeat in range(args.repeats):
        print(f"run {repeat + 1}/{args.repeats}", file=sys.stderr, flush=True)
        runs.append([coordination_overhead(k, n) for k, n in CELLS])
        starts.append(startup_and_memory(8))
        print(table(runs[-1]), file=sys.stderr, flush=True)

    def each(values: list[float]) -> str:
        return ", ".join(f"{value:.2f}" for value in values)

    rows = [
        [str(k), f"{n:,}", each([run[i].overhead_ms for run in runs]),
         each([run[i].bare_ms for run in runs]), each([run[i].between_rounds_ms for run in runs])]
        for i, (k, n) in enumerate(CELLS)
    ]  # fmt: skip
    memories = [memory for _, memory in starts]
    setup = (
        "Real `fedhpg-run` federations on loopback, CartPole MLPs of 10⁴ and 10⁶ parameters, "
        "one-step episodes (the agents' compute is tiny). Overhead = round wall time − the "
        "slowest agent's local wall time, median over 28 rounds, "
        f'{args.repeats} run{"s" if args.repeats > 1 else ""} a cell; "bare" is a pyzmq '
        "ROUTER and K forked DEALERs exchanging the same header and float32 vector and "
        "averaging (`benchmarks/bare_zmq.py`), in the same run. Between rounds: the server's "
        "wall time outside the rounds; the previous round's metrics line, TensorBoard event "
        "and checkpoint are written while the agents train, inside the next round. Start-up "
        "to the end of round 1 with K = 8 (demo GridWorld): "
        f"{', '.join(f'{seconds:.2f}' for seconds, _ in starts)} s; peak PSS of the whole "
        f"federation: {results_file.span(memories)} MiB."
    )
    results_file.write(
        "runtime",
        title="Coordination overhead per round",
        order=190,
        command=results_file.command_line("benchmarks.runtime"),
        measures=list(results_file.RUNTIME_CODE),
        setup=setup,
        tables=[{
            "columns": ["K", "parameters", "fedhpg overhead (ms)", "bare pyzmq + msgpack (ms)",
                        "between rounds (ms)"],
            "rows": rows,
            "summary": summary(runs),
        }],
    )  # fmt: skip


if __name__ == "__main__":
    main()
