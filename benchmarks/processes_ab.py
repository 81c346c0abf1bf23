"""One process per agent against the fused engine: K = 100 federations of one agent process
each (``benchmarks.scale``'s ``processes`` case), at this tree and at
:data:`benchmarks.engine_ab.BASELINE`, the two alternated run by run on the same machine.

Each agent of such a federation is a lone agent, so the comparison follows the lone agent's
row of :mod:`benchmarks.engine_ab`, with the processes' start-up and messages around it. The
commit's federation is its own ``fedhpg-run`` (the entry point its ``pyproject.toml`` names)
run with its package alone on the path; this tree's harness reads both federations' metrics.
Per run: whole-round env steps per second over rounds 2 to the last (from one θ̃ to the next,
evaluations excluded), the peak PSS of the whole federation, and where the CPU time of those
rounds went (:class:`CpuSplit`, from each thread's ``/proc/<pid>/task/<tid>/schedstat``).

    OMP_NUM_THREADS=1 python -m benchmarks.processes_ab             # 3 runs a side, 6 rounds
    python -m benchmarks.processes_ab --runs 1 --rounds 3 --no-table  # a spot check
    python -m benchmarks.processes_ab --tables-only                  # the table again
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from benchmarks import engine_ab, results_file
from benchmarks.results_file import span
from benchmarks.runtime import _children, _federation
from benchmarks.scale import CASES, MEASURES, round_walls, whole_round_rate

NAME = "engine_ab_processes"
RESULTS = Path(__file__).parent / "results" / f"{NAME}.json"


PARTS = {
    "server": "the server process",
    "main": "the agents' main threads (the socket: requests decoded, answers encoded)",
    "work": "the agents' job threads (the round: the engine, the result, the device's price)",
    "zmq": "the agents' ZeroMQ I/O threads",
}
"""Where a round's CPU time goes, :class:`CpuSplit`'s keys."""


class CpuSplit:
    """CPU milliseconds a round of the federation's processes, by :data:`PARTS`, over rounds
    2 to the last but one (from the end of round 1 to the end of that round: once the last
    round's record is written the processes begin to exit). Called by
    :func:`~benchmarks.runtime._federation` in a thread beside the federation."""

    def __init__(self, rounds: int) -> None:
        self.rounds = rounds
        self.ms: dict[str, float] = {}
        """Empty until read (never with fewer than 3 rounds)."""

    def __call__(self, launcher: int, metrics: Path) -> None:
        if self.rounds < 3:
            return
        before = _at_line(launcher, metrics, 1)
        after = _at_line(launcher, metrics, self.rounds - 1)
        if before is None or after is None:
            return
        spent: Counter[str] = Counter()
        for (pid, tid, part), ns in after.items():
            if (pid, tid, part) in before:
                spent[part] += ns - before[pid, tid, part]
        self.ms = {part: spent[part] / 1e6 / (self.rounds - 2) for part in PARTS}


def _at_line(launcher: int, metrics: Path, lines: int) -> dict[tuple[int, int, str], int] | None:
    """Every thread's CPU nanoseconds once ``metrics`` holds ``lines`` lines (None: the
    federation ended first), keyed (pid, tid, part)."""
    size = -1
    while True:
        try:
            now = metrics.stat().st_size
        except FileNotFoundError:
            now = 0
        if now != size:  # read only when it grew: it holds every agent's record
            size = now
            if now and metrics.read_bytes().count(b"\n") >= lines:
                return _thread_times(launcher)
        elif (stat := _stat(launcher)) is None or stat[0] == "Z":
            return None
        time.sleep(0.002)


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command's ")" (None: no such process):
    the state first, the start time 20th."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _thread_times(launcher: int) -> dict[tuple[int, int, str], int]:
    """The launcher's children's threads' CPU nanoseconds; its first child is the server
    (it is started before the agents), the others the agents."""

    def started(pid: int) -> int:
        stat = _stat(pid)
        return int(stat[19]) if stat is not None and len(stat) > 19 else 0

    times = {}
    for rank, pid in enumerate(sorted(_children(launcher), key=started)):
        try:
            tids = [int(tid) for tid in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            try:
                ns = int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
                name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            except (OSError, IndexError, ValueError):
                continue
            if rank == 0:
                part = "server"
            elif tid == pid:
                part = "main"
            else:
                part = "zmq" if name.startswith("ZMQbg") else "work"
            times[(pid, tid, part)] = ns
    return times


@dataclass(frozen=True)
class Run:
    """One federation's figures."""

    steps_per_s: float
    """Whole-round env steps per second, rounds 2 to the last."""
    peak_pss_mib: float
    cpu_ms: dict[str, float] = field(default_factory=dict)
    """CPU milliseconds a round by :data:`PARTS` (:class:`CpuSplit`; empty: not read)."""


def federation(tree: engine_ab.Tree, rounds: int, agents: int | None = None) -> Run:
    """One federation of one process per agent at ``tree`` (K = 100 unless ``agents``)."""
    case = replace(CASES["processes"], rounds=rounds)
    if agents is not None:
        case = replace(case, agents=agents)
    split = CpuSplit(rounds)
    with tempfile.TemporaryDirectory() as tmp:
        records, _, peak = _federation(
            case.overrides(), Path(tmp), sample_memory=True, poll_s=0.05,
            env=tree.env, command=tree.command, watch=split,
        )  # fmt: skip
    round_walls(records)
    trained = [r for r in records if r["agents"]][1:]  # round 1 is start-up
    return Run(whole_round_rate(trained), peak / 2**20, split.ms)


def save(this: list[Run], that: list[Run], against: str, rounds: int) -> None:
    RESULTS.write_text(json.dumps({
        "against": against, "rounds": rounds,
        "this": [asdict(r) for r in this], "that": [asdict(r) for r in that],
    }, indent=1) + "\n")  # fmt: skip


def load(path: Path = RESULTS) -> tuple[list[Run], list[Run], str]:
    """The stored runs (this tree's, the commit's) and the commit."""
    stored = json.loads(path.read_text())
    runs = [[Run(**r) for r in stored[side]] for side in ("this", "that")]
    return runs[0], runs[1], stored["against"]


def table(this: list[Run], that: list[Run], against: str) -> results_file.Table:
    ratios = [a.steps_per_s / b.steps_per_s for a, b in zip(this, that, strict=True)]
    rates = [[r.steps_per_s / 1e6 for r in runs] for runs in (this, that)]
    pss = [[r.peak_pss_mib for r in runs] for runs in (this, that)]
    rows = [
        ["whole-round env steps per second", f"{span(rates[0], '.3f')} M",
         f"{span(rates[1], '.3f')} M", f"{span(ratios, '.2f')}×"],
        ["peak PSS of the whole federation (MiB)", span(pss[0], ',.0f'),
         span(pss[1], ',.0f'), ""],
    ]  # fmt: skip
    more: dict[str, float] = {}
    if all(r.cpu_ms for r in (*this, *that)):
        for part, what in PARTS.items():
            ms = [[r.cpu_ms[part] for r in runs] for runs in (this, that)]
            rows.append([f"CPU ms a round: {what}", span(ms[0], ".1f"), span(ms[1], ".1f"), ""])
            more[part] = statistics.median(ms[0]) - statistics.median(ms[1])
    if min(ratios) >= 1.0:
        verdict = f"faster than {against}"
    elif max(ratios) < 1.0:
        verdict = f"slower than {against}"
    else:
        verdict = f"on either side of {against}"
    summary = (
        f"Run by run, this tree is {verdict} ({span(ratios, '.2f')}×); "
        f"peak PSS {span(pss[0], ',.0f')} MiB against {span(pss[1], ',.0f')}. Each agent "
        "there is a lone agent, so the figure follows the lone agent's row of the engine "
        "comparison above."
    )
    if more:
        summary += (
            " CPU a round, this tree's median minus the commit's: "
            + ", ".join(f"{PARTS[part].split(' (')[0]} {ms:+.1f} ms" for part, ms in more.items())
            + "."
        )
    return {"columns": ["", "this tree", against, "ratio"], "rows": rows, "summary": summary}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--against", default=engine_ab.BASELINE, help="the commit to compare with")
    parser.add_argument("--runs", type=int, default=3, help="federations a side (≥ 1)")
    parser.add_argument("--rounds", type=int, default=6, help="rounds a federation (≥ 2)")
    parser.add_argument("--no-table", action="store_true", help="print, write no table")
    parser.add_argument("--tables-only", action="store_true",
                        help="the table again from the stored runs")  # fmt: skip
    args = parser.parse_args()
    if args.runs < 1 or args.rounds < 2:
        parser.error("--runs ≥ 1 and --rounds ≥ 2")
    if args.tables_only:
        result = table(*load())
        results_file.rerender(NAME, [result])
        print(result["summary"])
        return
    this, that = engine_ab.THIS_TREE, engine_ab.baseline_tree(args.against)
    runs: dict[str, list[Run]] = {this.label: [], that.label: []}
    for index in range(args.runs):
        order = (this, that) if index % 2 == 0 else (that, this)
        for tree in order:
            run = federation(tree, args.rounds)
            runs[tree.label].append(run)
            cpu = ", ".join(f"{part} {ms:.1f}" for part, ms in run.cpu_ms.items())
            print(f"run {index + 1}, {tree.label}: {run.steps_per_s / 1e6:.3f} M env steps/s, "
                  f"peak PSS {run.peak_pss_mib:,.0f} MiB, CPU ms a round: {cpu or 'not read'}",
                  flush=True)  # fmt: skip
    result = table(runs[this.label], runs[that.label], args.against)
    print(result["summary"])
    if args.no_table:
        return
    save(runs[this.label], runs[that.label], args.against, args.rounds)
    default = args.runs == 3 and args.rounds == 6 and args.against == engine_ab.BASELINE
    words = ["OMP_NUM_THREADS=1 python -m benchmarks.processes_ab"]
    if not default:
        words.append(f"--against {args.against} --runs {args.runs} --rounds {args.rounds}")
    path = results_file.write(
        NAME,
        title="One process per agent against the fused engine",
        order=171,
        command=" ".join(words),
        measures=MEASURES,
        setup=(
            f"A federation of one process per agent, K = 100, {args.rounds} rounds, at this "
            f"commit and at {args.against} (the fused engine) alternated, {args.runs} runs "
            "each, the same machine; rounds 2 to the last."
        ),
        data=[str(RESULTS.relative_to(results_file.ROOT))],
        tables=[result],
        keep_summaries=False,
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
